"""`tacf eval`, `tacf track` and `tacf bench tracker`.

Only argparse-level code runs at import time; numpy, OpenCV and the tracker load inside the commands.
"""
from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from dataclasses import replace
from pathlib import Path

from tacf.argument_types import box, integer, source, take_negative_numbers
from tacf.stop_signals import interrupted_exit_code

log = logging.getLogger(__name__)

DEFAULT_TRACKERS = "tacf,tacf-authors,kcc,opencv-csrt,opencv-kcf,opencv-mosse,opencv-mil"
DEFAULT_OUT = Path("results/eval")
DEFAULT_DATA = Path("../shared/data/sequences")
RESULTS_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")  # `--results NAME=DIR`


def report_file(text: str) -> Path:
    """`--json OUT` of a benchmark: a path that cannot be written is refused when the command is parsed, not after
    the run it would lose (the missing folders on the way are made when it is written)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder; give a file name")
    folder = next(p for p in path.absolute().parents if p.exists())
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {folder} is a file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot write in {folder}")
    return path


def _segment_count(text: str) -> int:
    """`--tre K`: 0 (off) or K >= 2 segments; one segment is the one-pass run itself."""
    value = integer(0, what="a segment count")(text)
    if value == 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 0 (off) or at least 2 segments")
    return value


def _names(values: list[str] | None, default: str) -> list[str]:
    """Tracker names from `--trackers a,b c`: comma- or space-separated, duplicates dropped, each checked."""
    from .trackers import check_name

    raw = " ".join(values) if values else default
    names = list(dict.fromkeys(n for n in re.split(r"[,\s]+", raw) if n))     # "a b" quoted as one word too
    return [check_name(n) for n in names]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval", help="evaluate trackers on a dataset: one pass, shifted, TRE starts (success AUC, precision, FPS)",
        description="Run trackers side by side over every sequence of ROOT (layout detected: generic, OTB, "
                    "UAV123, UAVDT), and score result folders other toolkits wrote (--results) with them; write "
                    "result files, summary.json, summary.md and plots.")
    p.add_argument("root", metavar="ROOT", type=Path, help="dataset root folder")
    p.add_argument("--trackers", nargs="+", metavar="NAME",
                   help=f"tracker names, comma or space separated (default {DEFAULT_TRACKERS}; none with --results)")
    p.add_argument("--sequences", metavar="GLOB",
                   help="only sequences whose name matches (comma-separated globs; one without a / matches the "
                        "name's last part too)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, metavar="DIR", help="output folder (default %(default)s)")
    p.add_argument("--workers", type=integer(1), default=1, metavar="N", help="processes (default %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="rerun pairs that already have a result file (one of another length than the sequence, from "
                        "other --max-frames, always runs again)")
    p.add_argument("--ablation", action="store_true",
                   help="the paper's ablation: kcc, kcc+sa, kcc+da, kcc+ca, tacf-authors, and tacf, with the gains "
                        "over kcc (ignores --trackers)")
    p.add_argument("--ranges", type=Path, metavar="FILE",
                   help="UAV123 frame-range table (configSeqs.m or 'name folder first last' lines); UAV123 layout "
                        "only")
    p.add_argument("--max-frames", type=integer(1), metavar="N",
                   help="only the first N frames of each sequence (smoke tests; not a benchmark protocol)")
    p.add_argument("--shifts", type=integer(0), default=0, metavar="PX",
                   help="also start every pair from the 8 first boxes PX pixels away (kept in the frame as OTB's "
                        "shiftInitBB keeps them: stopped at the left and top borders, cut at the right and bottom "
                        "ones) and report how far each AUC moves and whether the trackers' differences stand out of "
                        "that")
    p.add_argument("--tre", type=_segment_count, default=0, metavar="K",
                   help="also start every pair at frames N/K, 2N/K, ... of each sequence (the starts of OTB's "
                        "temporal robustness, TRE; K = 10 is 5.5 times the one-pass work), report the mean over these "
                        "starts as --shifts does, and beside it OTB's TRE, which pools each sequence's frames")
    p.add_argument("--results", action="append", metavar="NAME=DIR",
                   help="also score the result files another toolkit wrote in DIR (pysot, got10k, pytracking: one "
                        "x,y,w,h row per frame, in the ground truth's pixel frame; the OTB / UAV123 MATLAB toolkit: "
                        "<sequence>_NAME.mat) as tracker NAME, one pass; repeatable. With --results and no --trackers, "
                        "nothing runs")
    p.add_argument("--absent", choices=("skip", "toolkit"), default="skip",
                   help="frames without a target (NaN or empty ground truth): skip leaves them out of the scores, as "
                        "got10k's UAV123 experiment does; toolkit counts them as pysot and the OTB/UAV123 MATLAB "
                        "toolkit do, a failure for success and a hit for precision (default %(default)s)")
    p.add_argument("--attributes", type=Path, metavar="FILE",
                   help="sequence attributes for the per-attribute scores: 'name ATTR ATTR ...' lines (default: the "
                        "benchmark's own, UAV123's att files or an attrs.txt in OTB's sequence folders, else SV, ARC, "
                        "LR and FM derived from the ground truth)")
    p.add_argument("--videos", action="store_true",
                   help="also write videos/<sequence>.mp4: every tracker's boxes and the ground truth on the frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_eval)

    p = subparsers.add_parser("track", help="track one target through a video file or an image folder",
                              description="Write one box line per frame and, with --video, an annotated mp4.")
    p.add_argument("source", metavar="SOURCE", type=source, help="video file or image folder")
    p.add_argument("--box", required=True, type=box, metavar="X,Y,W,H",
                   help="initial box, 0-based pixels, top-left x,y")
    take_negative_numbers(p)       # a box across the left or top border: --box -5,20,40,30
    p.add_argument("--out", type=Path, metavar="FILE", help="box file (default: standard output)")
    p.add_argument("--video", type=Path, metavar="FILE", help="annotated video to write (mp4v)")
    p.add_argument("--profile", metavar="P", help="TACF profile: paper, authors, kcc (default: the default profile)")
    p.add_argument("--tracker", metavar="NAME", help="any evaluation tracker name instead (e.g. opencv-csrt)")
    p.set_defaults(func=cmd_track)


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("tracker", help="per-stream tracker speed on decoded frames, CSRT alongside",
                                    description="Per-stream tracker speed on decoded frames, OpenCV CSRT alongside.")
    p.add_argument("root", metavar="ROOT", type=Path, nargs="?",
                   help=f"dataset root (default {DEFAULT_DATA} when present)")
    p.add_argument("--json", type=report_file, metavar="OUT", help="write the report here (default: standard output)")
    p.add_argument("--sequences", metavar="GLOB",
                   help="sequence globs (default: the UAV sequences, UAV123*/UAVDT*/DTB70*)")
    p.add_argument("--trackers", nargs="+", metavar="NAME",
                   help="trackers to time; the first is the subject (default tacf); opencv-csrt always runs")
    p.add_argument("--max-frames", type=integer(1), metavar="N", help="at most N frames per sequence")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_bench)


def _load(root: Path, pattern: str | None, ranges: Path | None = None, max_frames: int | None = None):
    from .datasets import detect_layout, load_sequences
    from .report import counted

    layout = detect_layout(root)
    if ranges is not None and layout != "uav123":
        raise ValueError(f"--ranges {ranges}: frame-range tables are for the UAV123 layout (data_seq/ + anno/), and "
                         f"{root} is in the {layout} layout")
    seqs = load_sequences(root, pattern, layout=layout, ranges=ranges)
    if pattern and not seqs:
        names = [s.name for s in load_sequences(root, layout=layout, ranges=ranges)]
        listed = ", ".join(names[:20]) + (f" and {len(names) - 20} more" if len(names) > 20 else "")
        raise ValueError(f"no sequences in {root} matching {pattern!r}; it has {listed or 'none'}")
    if max_frames is not None:
        seqs = [replace(s, frames=s.frames[:max_frames], gt=s.gt[:max_frames]) for s in seqs]
    log.info("%s: %s layout, %s%s", root, layout, counted(len(seqs), "sequence"),
             f" matching {pattern!r}" if pattern else "")
    return seqs


def _imported(specs: list[str] | None, trackers: list[str], seqs, allow_longer: bool) -> dict[str, dict]:
    """{NAME: {sequence name: (boxes, times)}} from `--results NAME=DIR` specs; ValueError naming every problem."""
    from collections import Counter

    from .runner import otb_stem, read_imported_run

    # A two-target OTB sequence's result may go by the bare name only when no other target of it is scored.
    stems = Counter(otb_stem(s.name) for s in seqs)
    imported: dict[str, dict] = {}
    for spec in specs or []:
        name, equals, folder = (part.strip() for part in spec.partition("="))
        if not equals or not RESULTS_NAME.fullmatch(name) or not folder:
            raise ValueError(f"bad --results {spec!r}: use NAME=DIR, NAME of letters, digits and _ . + -")
        if name in trackers or name in imported:
            raise ValueError(f"--results {name}: the name is taken by a tracker or another --results")
        if not Path(folder).is_dir():
            raise ValueError(f"--results {name}: {folder} is not a folder")
        runs, missing = {}, []
        for seq in seqs:
            try:
                runs[seq.name] = read_imported_run(Path(folder), seq, allow_longer, stems[otb_stem(seq.name)] == 1,
                                                   toolkit_name=name)
            except FileNotFoundError:
                missing.append(seq.name)
            except ValueError as exc:
                raise ValueError(f"--results {name}: {exc}") from None
        if missing:
            listed = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
            raise ValueError(f"--results {name}: {folder} has no result for {len(missing)} of the {len(seqs)} "
                             f"sequences ({listed}; looked for <sequence>.txt, <last part>.txt, <last part>/"
                             f"<last part>_001.txt and <last part>_{name}.mat, <name>.N, <name>_N and <name> for a "
                             "target <name>-N); --sequences selects the ones it has")
        imported[name] = runs
    return imported


def cmd_eval(args: argparse.Namespace) -> int:
    from . import metrics, report
    from .attributes import attributes_of, read_attribute_table
    from .provenance import provenance
    from .runner import OutOfRoom, Start, pending_jobs, run_jobs, shifted_starts, temporal_starts
    from .text_files import CannotWrite, write_atomically
    from .trackers import ABLATION

    if args.ablation and args.trackers:
        log.warning("--ablation runs %s; --trackers ignored", ", ".join(ABLATION))
    try:
        default = "" if args.results else DEFAULT_TRACKERS  # scoring result files only, unless asked
        trackers = list(ABLATION) if args.ablation else _names(args.trackers, default)
        seqs = _load(args.root, args.sequences, args.ranges, args.max_frames)
        # a result longer than the sequence scores its first frames when only they were asked for
        allow_longer = args.max_frames is not None
        imported = _imported(args.results, trackers, seqs, allow_longer)
        attribute_table = read_attribute_table(args.attributes) if args.attributes else None
    except (ValueError, OSError) as exc:
        log.error("%s", exc)
        return 2
    if not seqs:
        log.error("no sequences in %s", args.root)
        return 2
    try:  # before any pair runs: every one would fail to record, and the report after them
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        log.error("--out %s: cannot make this folder: %s", args.out, exc.strerror)
        return 2
    if imported and (args.shifts or args.tre):
        log.info("imported results (%s) are scored one pass only", ", ".join(imported))
    protocols = {}  # robustness protocol: its starts, the one-pass start first
    if args.shifts:
        protocols["shifts"] = shifted_starts(args.shifts)
    if args.tre:
        protocols["tre"] = temporal_starts(args.tre)
    # Every protocol begins with the one-pass start (results in out_dir itself): it runs once.
    starts = [Start()] + [start for its_starts in protocols.values() for start in its_starts[1:]]
    jobs = [job for start in starts for job in pending_jobs(trackers, seqs, args.out, args.force, start, allow_longer)]
    skipped = sum(len(trackers) * len(start.sequences(seqs)) for start in starts) - len(jobs)
    if skipped:
        log.info("%d (tracker, sequence) results already recorded in %s; skipped (use --force to rerun)",
                 skipped, args.out)
    try:
        outcomes = run_jobs(jobs, workers=args.workers, progress=not args.no_progress)
    except KeyboardInterrupt:
        log.error("interrupted: the pairs finished are recorded in %s, and the same command goes on from there",
                  args.out)
        return interrupted_exit_code()
    except OutOfRoom as stop:
        log.error("%s on %s failed: %s; stopped, with %d of the %d pairs not done (each would fail alike): the pairs "
                  "finished are recorded in %s, and the same command goes on from there", stop.outcome.tracker,
                  stop.outcome.seq_name, stop.outcome.error, stop.not_done, len(jobs), args.out)
        return 1
    failed = [o for o in outcomes if o.error]
    for o in failed:
        log.error("%s on %s failed: %s", o.tracker, o.seq_name, o.error)
    summary, reports = report.summarize(args.out, trackers, seqs, imported, args.absent, allow_longer)
    for protocol, its_starts in protocols.items():
        per_start = {start.label: report.summarize(start.directory(args.out), trackers, start.sequences(seqs),
                                                   absent=args.absent,
                                                   allow_longer=allow_longer and start.from_first_frame)[0]
                     for start in its_starts}
        # OTB pools the frames of a sequence's TRE starts (see report.robustness); its shifted starts weigh alike
        frames_scored = None if protocol != "tre" else {
            start.label: {part.name: metrics.frames_scored(part.gt, args.absent) for part in start.sequences(seqs)}
            for start in its_starts}
        summary[report.ROBUSTNESS_KEYS[protocol]] = report.robustness(per_start, trackers, protocol,
                                                                      frames_scored=frames_scored)
    lost_flag = report.lost_flag_summary(reports)
    if lost_flag["trackers"]:
        summary["lost_flag"] = lost_flag
    source, attributes = attributes_of(seqs, attribute_table)
    summary["attributes"] = report.attribute_scores(summary, attributes, source)
    summary["run"] = {**provenance(args), "pairs_run": len(jobs), "pairs_recorded_before": skipped}
    try:
        paths = report.write_reports(args.out, summary, reports, seqs)
        if args.videos:
            paths["videos"] = _write_videos(args.out / "videos", seqs, reports, progress=not args.no_progress)
        table = report.markdown_table(summary)
        if args.ablation:
            table = report.ablation_table(summary)
            write_atomically(Path(args.out) / "ablation.md", table)
    except CannotWrite as exc:
        log.error("%s; the results of the pairs are recorded in %s, and the same command writes the reports from "
                  "them", exc, args.out)
        return 1
    table += report.analysis_tables(summary)
    sys.stdout.write(table)
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return 1 if failed else 0


def _write_videos(folder: Path, seqs, reports, progress: bool) -> Path:
    """videos/<sequence>.mp4 for every sequence, each tracker in its colour of the plots."""
    from tqdm import tqdm

    from .report import tracker_colour
    from .video import write_comparison_video

    for seq in tqdm(seqs, desc="videos", unit="seq", disable=not progress):
        tracks = [(r.name, tracker_colour(i), r.boxes[seq.name]) for i, r in enumerate(reports) if seq.name in r.boxes]
        write_comparison_video(seq, tracks, folder / f"{seq.name}.mp4")
    return folder


def cmd_track(args: argparse.Namespace) -> int:
    from .trackers import check_name, make_tracker
    from .video import track_source

    try:
        if args.tracker and args.profile:
            raise ValueError("give --profile or --tracker, not both")
        name = check_name(args.tracker or (f"tacf-{args.profile}" if args.profile else "tacf"))
        tracker = make_tracker(name)
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    try:
        n = track_source(tracker, Path(args.source), args.box, args.out, args.video)
    except BrokenPipeError:
        raise                   # stdout's reader left: not an error of the source or the output files
    except (ValueError, FileNotFoundError, OSError) as exc:
        log.error("%s", exc)
        return 2
    log.info("%s: %d frames%s%s", name, n, f", boxes in {args.out}" if args.out else "",
             f", video in {args.video}" if args.video else "")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from .bench import UAV_PREFIXES, bench, is_uav
    from .provenance import provenance
    from .report import counted, strict_json
    from .text_files import CannotWrite, write_atomically

    root = args.root
    if root is None:
        if not DEFAULT_DATA.is_dir():
            log.error("no ROOT given and %s does not exist", DEFAULT_DATA)
            return 2
        root = DEFAULT_DATA
    try:
        trackers = _names(args.trackers, "tacf")
        seqs = _load(root, args.sequences, max_frames=args.max_frames)
    except (ValueError, OSError) as exc:
        log.error("%s", exc)
        return 2
    if not args.sequences:
        uav = [s for s in seqs if is_uav(s.name)]
        if seqs and not uav:
            log.error("none of the %d sequences of %s is named %s* (the UAV sequences timed by default); "
                      "--sequences chooses others, '*' all of them", len(seqs), root, "*, ".join(UAV_PREFIXES))
            return 2
        seqs = uav
        log.info("timing the %s among them (%s*; --sequences chooses others)",
                 counted(len(seqs), "UAV sequence"), "*, ".join(UAV_PREFIXES))
    if not seqs:
        log.error("no sequences to benchmark in %s", root)
        return 2
    result = {**bench(trackers, seqs, progress=not args.no_progress), "run": provenance(args)}
    text = strict_json(result)      # no speed (a tracker that failed on every sequence) is null, as in summary.json
    if args.json:
        try:
            write_atomically(args.json, text)
        except CannotWrite as exc:      # minutes of timing are not lost for a full disk: the report goes to stdout
            log.error("%s; the report follows on standard output", exc)
            sys.stdout.write(text)
            return 1
        over, peer = result["ratio_over"], result["peers"].get("opencv-csrt", result)
        headline = (f"{result['tracker']}: {result['fps']:.1f} fps on {result['cores']:.2f} cores"
                    if result["sequences"] else f"{result['tracker']}: no sequence finished")
        if not over["sequences"]:   # a Ctrl-C in the first sequence, or every pair failed: no speed to divide
            log.info("%s; no ratio to opencv-csrt (no sequence that both finished); wrote %s", headline, args.json)
        elif len(result["sequences"]) == len(over["sequences"]) == len(peer["sequences"]):
            log.info("%s (opencv-csrt %.1f fps, %.2fx); wrote %s", headline, peer["fps"],
                     result["ratio_to_opencv-csrt"], args.json)
        else:   # a failed pair or a Ctrl-C: side by side, the speeds over the same sequences, the ratio's
            log.info("%s over its %s; over the %d it and opencv-csrt both finished, %.1f against %.1f fps "
                     "(%.2fx); wrote %s", headline, counted(len(result["sequences"]), "sequence"),
                     len(over["sequences"]), over["fps"], over["peer_fps"], result["ratio_to_opencv-csrt"], args.json)
    else:
        sys.stdout.write(text)
    failed = sum(len(report["failed"]) for report in [result, *result["peers"].values()])
    if failed:
        log.error("%d (tracker, sequence) pairs failed (each tracker's `failed` in the report); their speeds are "
                  "left out", failed)
    if result["interrupted"]:
        print("tacf bench: interrupted; the report holds the pairs finished", file=sys.stderr)
        return interrupted_exit_code()
    return 1 if failed else 0
