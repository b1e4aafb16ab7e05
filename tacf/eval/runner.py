"""The frame loop, written once: run trackers over sequences, time them, write resumable result files.

Result tree (got10k layout, docs ECOSYSTEM.md 3.5):
    <out>/<tracker>/<seq>.txt                  x,y,w,h per frame, 1-based, %.3f, line 1 = the init box
    <out>/<tracker>/times/<seq>_time.txt       seconds of tracker time per frame (init on line 1)
    <out>/<tracker>/confidence/<seq>.txt       pme,ok per frame: the tracker's own confidence and lost flag
<seq> is the sequence name relative to the dataset root, so it may contain folders (UAV123_10fps/wakeboard7).
Runs started from a shifted first box (`tacf eval --shifts`) go to <out>/shifted/<dx><dy>/, runs started at a
later frame (`tacf eval --tre`) to <out>/tre/<segment>of<segments>/, in the same layout.
Timing covers the init/update calls only (time.perf_counter), never the image decoding, nor a process's first run
of each tracker (`warm_up`). Times are written with 9 significant digits, so that a fast tracker's microseconds
keep their precision (files of 6 decimals, written before, read the same way).

Result folders written by other toolkits (`tacf eval --results NAME=DIR`) are read by `read_imported_run`.
"""
from __future__ import annotations

import errno
import io
import itertools
import logging
import multiprocessing
import re
import signal
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath

import numpy as np

from ..images import read_image
from .datasets import Sequence, read_boxes, write_boxes
from .datasets.base import parse_boxes, write_rows
from .text_files import CannotWrite, read_text
from .trackers import BoxTracker, make_tracker, settings_of

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackRun:
    """One tracker over one frame stream: N x 4 0-based boxes (row 0 = init box), seconds, ok and pme per frame,
    and the process's CPU seconds (all threads) during the tracker calls."""

    boxes: np.ndarray
    times: np.ndarray
    ok: np.ndarray
    pme: np.ndarray
    cpu_seconds: float


def read_frame(path: Path) -> np.ndarray:
    """A BGR uint8 image (tacf.images.read_image); FileNotFoundError instead of OpenCV's silent None."""
    img = read_image(Path(path))
    if img is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return img


def iter_frames(paths: Iterable[Path]) -> Iterator[np.ndarray]:
    for p in paths:
        yield read_frame(p)


def track_frames(tracker: BoxTracker, frames: Iterable[np.ndarray], init_box) -> TrackRun:
    """Init on the first frame with `init_box`, update on the rest; only the tracker calls are timed, in wall and
    CPU time."""
    boxes, times, oks, pmes = [], [], [], []
    it = iter(frames)
    first = next(it, None)
    if first is None:
        raise ValueError("no frames to track")
    box = tuple(float(v) for v in init_box)
    cpu, t0 = time.process_time(), time.perf_counter()
    tracker.init(first, box)
    times.append(time.perf_counter() - t0)
    cpu_seconds = time.process_time() - cpu
    boxes.append(box)
    oks.append(True)
    pmes.append(np.nan)
    for frame in it:
        cpu, t0 = time.process_time(), time.perf_counter()
        box = tracker.update(frame)
        times.append(time.perf_counter() - t0)
        cpu_seconds += time.process_time() - cpu
        boxes.append(tuple(float(v) for v in box))
        oks.append(bool(tracker.ok))
        pmes.append(float(tracker.pme))
    return TrackRun(np.asarray(boxes, dtype=np.float64), np.asarray(times), np.asarray(oks), np.asarray(pmes),
                    cpu_seconds)


def shifted_box(box, shift: tuple[int, int], frame_hw) -> np.ndarray:
    """box (x, y, w, h) moved by shift = (dx, dy), then kept inside the frame as OTB's shiftInitBB keeps it: a left
    or top edge beyond the border is moved onto it, and the size cut at the right and bottom borders."""
    x, y = max(box[0] + shift[0], 0.0), max(box[1] + shift[1], 0.0)
    moved = np.array([x, y, min(box[2], frame_hw[1] - x), min(box[3], frame_hw[0] - y)], dtype=np.float64)
    if moved[2] <= 0 or moved[3] <= 0:
        raise ValueError(f"the first box {list(box)} moved by {shift} lies outside the {frame_hw[1]}x{frame_hw[0]} "
                         "frame")
    return moved


def track_sequence(tracker: BoxTracker, seq: Sequence, shift: tuple[int, int] = (0, 0)) -> TrackRun:
    """One-pass evaluation: init from the first ground-truth box, moved by shift = (dx, dy) pixels and kept in the
    frame (`shifted_box`); frames are decoded lazily outside the timer."""
    if not np.isfinite(seq.gt[0]).all() or seq.gt[0, 2] <= 0 or seq.gt[0, 3] <= 0:
        raise ValueError(f"{seq.name}: the first ground-truth box {seq.gt[0].tolist()} cannot start a track")
    first = read_frame(seq.frames[0])
    box = seq.gt[0] if shift == (0, 0) else shifted_box(seq.gt[0], shift, first.shape[:2])
    return track_frames(tracker, itertools.chain([first], iter_frames(seq.frames[1:])), box)


WARM_UP_FRAMES = 3
_warmed_up: set[str] = set()        # the tracker names this process has run once, untimed


def warm_up(name: str, seq: Sequence, shift: tuple[int, int] = (0, 0)) -> None:
    """Run tracker `name` untimed on the first frames of `seq`, the first time this process runs it: what a process
    pays once (loading the compiled fHOG from numba's cache, OpenCV's lazy set-up) is no cost of a sequence, and
    would otherwise be charged to whichever sequence comes first."""
    if name not in _warmed_up:
        first = replace(seq, frames=seq.frames[:WARM_UP_FRAMES], gt=seq.gt[:WARM_UP_FRAMES])
        track_sequence(make_tracker(name), first, shift)
        _warmed_up.add(name)


@dataclass(frozen=True)
class Start:
    """Where the runs of one pass start. One-pass evaluation starts on frame 1 from its ground-truth box; `shift`
    moves that box by (dx, dy) pixels (OTB's spatial robustness); `segment` of `segments` starts at frame
    segment * N // segments of each sequence, from the first ground-truth box there or later (the starts of OTB's
    temporal robustness, TRE), and scores the frames from there on."""

    shift: tuple[int, int] = (0, 0)
    segment: int = 0
    segments: int = 1

    @property
    def label(self) -> str:
        return f"{self.segment}/{self.segments}" if self.segments > 1 else f"{self.shift[0]:+d},{self.shift[1]:+d}"

    @property
    def from_first_frame(self) -> bool:
        """Whether the runs start on the sequence's first frame, whatever its length: a longer run (`rows_fit`) then
        holds these runs' boxes, whereas a TRE start moves with the length."""
        return not self.segment

    def describe(self) -> str:
        """For messages; empty for the one-pass start."""
        if self.segment:
            return f"started at {self.label} of the sequence"
        return f"first box moved by {self.shift}" if self.shift != (0, 0) else ""

    def directory(self, out_dir: Path) -> Path:
        """The result tree of these runs: out_dir itself for the one-pass start."""
        if self.segment:
            return Path(out_dir) / "tre" / f"{self.segment}of{self.segments}"
        if self.shift != (0, 0):
            return Path(out_dir) / "shifted" / f"{self.shift[0]:+d}{self.shift[1]:+d}"
        return Path(out_dir)

    def sequence(self, seq: Sequence) -> Sequence | None:
        """The part of `seq` these runs track: from the first box at or after the start frame that leaves 2 frames
        to track, else (the target absent to the end) from the last such box before it, as OTB's last start is the
        last usable one, so that the sequence stays in every start's report; None when no box leaves 2 frames."""
        if not self.segment:
            return seq
        segment_start = self.segment * len(seq) // self.segments
        startable = np.isfinite(seq.gt).all(axis=1) & (seq.gt[:, 2] > 0) & (seq.gt[:, 3] > 0)
        candidates = np.flatnonzero(startable[:len(seq) - 1])
        if not len(candidates):
            return None
        later = candidates[candidates >= segment_start]
        first = int(later[0]) if len(later) else int(candidates[-1])
        if first < segment_start:
            log.info("%s: no usable box from frame %d of %d on; start %s starts at frame %d", seq.name,
                     segment_start + 1, len(seq), self.label, first + 1)
        return replace(seq, frames=seq.frames[first:], gt=seq.gt[first:])

    def sequences(self, seqs: list[Sequence]) -> list[Sequence]:
        return [part for part in map(self.sequence, seqs) if part is not None]


def shifted_starts(pixels: int) -> list[Start]:
    """The given start, then the 8 first boxes `pixels` away (size kept, but kept in the frame by `shifted_box`)."""
    return [Start()] + [Start((dx * pixels, dy * pixels)) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]


def temporal_starts(segments: int) -> list[Start]:
    """Starts at frames 0, N // segments, 2 N // segments, ... of each sequence."""
    return [Start(segment=i, segments=segments) for i in range(segments)]


def result_path(out_dir: Path, tracker: str, seq_name: str) -> Path:
    return Path(out_dir) / tracker / f"{seq_name}.txt"


def times_path(out_dir: Path, tracker: str, seq_name: str) -> Path:
    return Path(out_dir) / tracker / "times" / f"{seq_name}_time.txt"


def confidence_path(out_dir: Path, tracker: str, seq_name: str) -> Path:
    return Path(out_dir) / tracker / "confidence" / f"{seq_name}.txt"


SETTINGS = "settings "        # in the confidence file's header: settings_of() the tracker that made the result


def write_run(out_dir: Path, tracker: str, seq_name: str, run: TrackRun) -> None:
    """Times and confidence first, boxes last: the box file's presence marks a complete, resumable result."""
    write_rows(times_path(out_dir, tracker, seq_name), run.times, "%.9g")
    write_rows(confidence_path(out_dir, tracker, seq_name), np.column_stack([run.pme, run.ok]), "%.3f,%d",
               "pme,ok: the tracker's peak-to-median energy (nan: none) and lost flag (0) per frame\n"
               f"{SETTINGS}{settings_of(tracker)}")
    write_boxes(result_path(out_dir, tracker, seq_name), run.boxes, one_based=True)


def recorded_settings(out_dir: Path, tracker: str, seq_name: str) -> str | None:
    """settings_of() the tracker that recorded this result, from its confidence file (None: not said there)."""
    path = confidence_path(out_dir, tracker, seq_name)
    if not path.is_file():
        return None
    with path.open() as lines:
        for line in itertools.islice(lines, 2):
            if line.startswith("# " + SETTINGS):
                return line[len("# " + SETTINGS):].strip()
    return None


def read_confidence(out_dir: Path, tracker: str, seq_name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(pme, ok) per frame of a recorded result, or None for results recorded without them."""
    path = confidence_path(out_dir, tracker, seq_name)
    if not path.is_file():
        return None
    rows = np.loadtxt(path, delimiter=",", ndmin=2)
    return rows[:, 0], rows[:, 1].astype(bool)


def rows_fit(rows: int, frames: int, allow_longer: bool = False) -> bool:
    """Whether a result of `rows` boxes scores a sequence of `frames` frames: one box per frame, or more with
    `allow_longer` (only the first frames of the sequence were asked for; a track's first boxes do not depend on
    the frames after them)."""
    return rows == frames or (rows > frames and allow_longer)


def read_run(out_dir: Path, tracker: str, seq_name: str) -> tuple[np.ndarray, np.ndarray]:
    """(0-based N x 4 boxes, seconds per frame) of a recorded result; times are NaN if their file is missing."""
    boxes = read_boxes(result_path(out_dir, tracker, seq_name), one_based=True)
    tp = times_path(out_dir, tracker, seq_name)
    times = np.atleast_1d(np.loadtxt(tp, ndmin=1)) if tp.is_file() else np.full(len(boxes), np.nan)
    return boxes, times


# tacf's name for target N of a two-target OTB sequence (groundtruth_rect.N.txt): Jogging-1, Human4-2
_OTB_TARGET = re.compile(r"(.+)-(\d+)")


def otb_stem(seq_name: str) -> str:
    """The sequence name without the target number of a two-target OTB sequence (OTB100/Jogging-1: OTB100/Jogging)."""
    m = _OTB_TARGET.fullmatch(seq_name)
    return m.group(1) if m else seq_name


def _result_names(name: str, bare: bool) -> list[str]:
    """The names other toolkits may give the sequence tacf calls `name`: itself (ours, pysot's) and, for target N
    of a two-target OTB sequence <stem>-<N>, got10k's <stem>.<N>, pytracking's <stem>_<N> and, with `bare`,
    got10k's <stem> (Human4: it names a folder's only annotated target by the folder)."""
    m = _OTB_TARGET.fullmatch(name)
    if not m:
        return [name]
    stem, target = m.groups()
    return [name, f"{stem}.{target}", f"{stem}_{target}"] + ([stem] if bare else [])


def _imported_files(results_dir: Path, seq_name: str, bare: bool = True,
                    toolkit_name: str | None = None) -> tuple[Path, Path | None, str] | None:
    """(result file, times file or None, its layout: "txt", "vot" for pysot's VOT layout, "mat" for the MATLAB
    toolkit's) of a sequence in another toolkit's result folder, or None.

    Result files: <dir>/<seq name>.txt (ours, got10k's: the name relative to the dataset root), <dir>/<last part>.txt
    (pysot's, pytracking's), <dir>/<last part>/<last part>_001.txt (pysot's VOT layout, and got10k's and pysot's
    GOT-10k layout) or <dir>/<last part>_<toolkit_name>.mat (the OTB / UAV123 MATLAB toolkit's, and the TACF
    authors' code's), the last part also under the other names of `_result_names`. Times: <dir>/times/<that
    path>_time.txt (ours, got10k's) or <last part>_time.txt beside the box file (pytracking's; got10k's and pysot's
    <last part>/<last part>_time.txt); a .mat file holds its run's fps instead."""
    results_dir = Path(results_dir)
    parent = PurePosixPath(seq_name).parent
    for name in _result_names(PurePosixPath(seq_name).name, bare):
        for relative, layout in ((str(parent / name), "txt"), (name, "txt"), (f"{name}/{name}_001", "vot")):
            box_file = results_dir / f"{relative}.txt"
            if box_file.is_file():
                times = [results_dir / "times" / f"{relative}_time.txt", box_file.with_name(f"{name}_time.txt")]
                return box_file, next((t for t in times if t.is_file()), None), layout
        mat_file = results_dir / f"{name}_{toolkit_name}.mat"
        if toolkit_name and mat_file.is_file():
            return mat_file, None, "mat"
    return None


def _read_toolkit_mat(mat_file: Path) -> tuple[np.ndarray, float]:
    """(0-based boxes, frames per second) of the MATLAB toolkit's <seq>_<tracker>.mat: a cell `results` whose first
    struct is the one-pass run (the later ones are SRE's or TRE's), its `res` the 1-based x,y,w,h rows (type
    'rect') and its `fps` the speed the toolkit measured."""
    from scipy.io import loadmat

    data = mat_file.read_bytes()   # outside the try: a file that cannot be read says so as an OSError of its own
    try:
        results = loadmat(io.BytesIO(data), simplify_cells=True)["results"]
    except Exception as exc:   # noqa: BLE001 - scipy's parser, not ours, fails here
        # A v7.3 (HDF5) file raises NotImplementedError, a file without `results` KeyError, but a short or damaged
        # one whatever scipy's parser trips over: IndexError, TypeError, OSError, zlib.error, UnboundLocalError,
        # ZeroDivisionError ... (scipy 1.13-1.17 alike, e.g. IndexError for any 20-126 bytes of text).
        raise ValueError(f"{mat_file}: not a MATLAB toolkit result (a `results` cell in a v5/v7 MAT file): "
                         f"{type(exc).__name__}: {exc}") from None
    run = results[0] if isinstance(results, list) else results   # a 1 x 1 cell comes out as its struct
    if not isinstance(run, dict) or "res" not in run:
        raise ValueError(f"{mat_file}: `results` holds no struct with a `res` field")
    if run.get("type", "rect") != "rect":
        raise ValueError(f"{mat_file}: results of type {run['type']!r}; only 'rect' (x,y,w,h) results are read")
    boxes = np.atleast_2d(np.array(run["res"], dtype=np.float64))
    if boxes.ndim != 2 or boxes.shape[1] != 4:     # a 4 x N matrix read N x 4 would scramble every box
        raise ValueError(f"{mat_file}: `res` is {boxes.shape}, not one x,y,w,h row per frame")
    boxes[:, :2] -= 1.0   # 1-based, as the ground truth the toolkit compares them with
    return boxes, float(run.get("fps", np.nan))


def _read_pysot_vot(box_file: Path, first_box: np.ndarray) -> np.ndarray:
    """0-based boxes of pysot's <seq>/<seq>_001.txt. Its one-pass (long-term) results write `1` on line 1 for the
    init frame instead of a box: that frame gets the first ground-truth box, the one it was given. VOT's reset-based
    results also write `2` (a failure) and `0` (a frame skipped before the reset): not a one-pass track, refused."""
    lines = read_text(box_file).splitlines()
    for lineno, line in enumerate(lines, 1):
        if line.strip() in ("0", "2"):
            raise ValueError(f"{box_file}:{lineno}: '{line.strip()}' marks a VOT reset (2: a failure, 0: a frame "
                             "skipped before the reset): these are VOT reset-based results, not one-pass results")
    init = bool(lines) and lines[0].strip() == "1"
    if init:
        lines[0] = "nan,nan,nan,nan"  # keeps the line numbers of parse errors
    boxes = parse_boxes(lines, box_file, one_based=True)
    if init:
        boxes[0] = first_box
    return boxes


def read_imported_run(results_dir: Path, seq: Sequence, allow_longer: bool = False, bare: bool = True,
                      toolkit_name: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(0-based N x 4 boxes, seconds per frame or NaN) of `seq` from a result folder another toolkit wrote.

    Box files are in the pixel frame of the dataset's ground-truth files, as every toolkit compares them (1-based
    for the MATLAB-made benchmarks), so they are read the way the ground truth is. One row per frame, the first
    being the init box; more rows than frames only with `allow_longer` (the first frames of a sequence were
    asked for). `bare`: a two-target OTB sequence's result may go by the bare sequence name (no other target of
    it is scored). `toolkit_name`: the tracker's name in the MATLAB toolkit's file names (<seq>_<name>.mat).
    Raises FileNotFoundError or ValueError saying what is wrong."""
    found = _imported_files(results_dir, seq.name, bare, toolkit_name)
    if found is None:
        raise FileNotFoundError(f"no result for {seq.name} in {results_dir}")
    box_file, times_file, layout = found
    fps = np.nan
    if layout == "mat":
        boxes, fps = _read_toolkit_mat(box_file)
    elif layout == "vot":
        boxes = _read_pysot_vot(box_file, seq.gt[0])
    else:
        boxes = read_boxes(box_file, one_based=True)
    if not rows_fit(len(boxes), len(seq), allow_longer):
        raise ValueError(f"{box_file}: {len(boxes)} boxes for the {len(seq)} frames of {seq.name}")
    times = np.full(len(seq), 1.0 / fps if fps > 0 else np.nan)   # the toolkit keeps one speed per run
    if times_file is not None:
        try:  # got10k writes a column per repetition: the first is the run of the <name>_001 boxes
            recorded = np.loadtxt(times_file, delimiter=",", ndmin=2)[:, 0]
        except ValueError as exc:
            raise ValueError(f"{times_file}: {exc}") from None
        if len(recorded) >= len(seq):
            times = recorded[: len(seq)]
        else:
            log.warning("%s: %d times for %d frames; its speed is left out", times_file, len(recorded), len(seq))
    return boxes[: len(seq)], times


@dataclass(frozen=True)
class Job:
    tracker: str
    seq: Sequence
    out_dir: Path
    start: Start = Start()


@dataclass(frozen=True)
class JobOutcome:
    tracker: str
    seq_name: str
    frames: int
    seconds: float
    error: str | None = None
    no_room: bool = False       # its result could not be written for want of room (NO_ROOM): run_jobs stops


# A result that cannot be written for these (a full disk or quota, a file-size limit, a read-only disk) stops the
# run: every pair after it would track its sequence for minutes and fail alike.
NO_ROOM = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


class OutOfRoom(Exception):
    """run_jobs stopped at `outcome`, a pair whose result could not be written (JobOutcome.no_room), with
    `not_done` pairs not done (not run, or ended running)."""

    def __init__(self, outcome: JobOutcome, not_done: int):
        super().__init__(outcome.error)
        self.outcome, self.not_done = outcome, not_done


def failed_outcome(job: Job, error: str) -> JobOutcome:
    """The outcome of a pair that failed with `error`, followed by the start of the pair's runs if not one-pass."""
    start = job.start.describe()
    return JobOutcome(job.tracker, job.seq.name, 0, 0.0, f"{error} ({start})" if start else error)


def run_job(job: Job) -> JobOutcome:
    """Run one (tracker, sequence) pair and record it; errors are returned, not raised. What an earlier run left
    for the pair goes first: a pair that failed was scored from it (a `--force` run whose frame had become
    unreadable, a TRE start moved by other --max-frames)."""
    for path in (result_path, times_path, confidence_path):
        path(job.out_dir, job.tracker, job.seq.name).unlink(missing_ok=True)
    try:
        import cv2

        cv2.setNumThreads(1)  # one core per job: fair per-stream numbers and no oversubscription
        warm_up(job.tracker, job.seq, job.start.shift)
        run = track_sequence(make_tracker(job.tracker), job.seq, job.start.shift)
        write_run(job.out_dir, job.tracker, job.seq.name, run)
        return JobOutcome(job.tracker, job.seq.name, len(run.boxes), float(run.times.sum()))
    except CannotWrite as exc:  # the file and the reason say it all: no traceback
        outcome = replace(failed_outcome(job, str(exc)), no_room=exc.errno in NO_ROOM)
        if not outcome.no_room:     # one that stops the run is told as it stops it
            log.error("%s on %s failed: %s", job.tracker, job.seq.name, outcome.error)
        return outcome
    except Exception as exc:  # noqa: BLE001 - one failed pair must not stop the others
        outcome = failed_outcome(job, f"{type(exc).__name__}: {exc}")
        log.exception("%s on %s failed: %s", job.tracker, job.seq.name, outcome.error)
        return outcome


def is_recorded(out_dir: Path, tracker: str, seq: Sequence, allow_longer: bool = False,
                first_box: np.ndarray | None = None) -> bool:
    """Whether out_dir holds a result of `tracker` that scores `seq` (see `rows_fit`); one of another length, left
    by a run with other --max-frames or frame ranges, is not, nor one that cannot be read, nor, given `first_box`,
    one whose first row (the box the tracker started from) is another: a TRE start moves with the sequence's
    length, so a run with other --max-frames can leave a result of the same length from another frame. Nor is one
    recorded with other settings (`settings_of`): `tacf` names the default profile, whose boxes change with it, and
    a resumed run mixed the boxes of two versions under one name."""
    path = result_path(out_dir, tracker, seq.name)
    if not path.is_file():
        return False
    try:
        boxes = read_boxes(path, one_based=True)
    except ValueError as exc:
        log.warning("%s; run again", exc)
        return False
    if not rows_fit(len(boxes), len(seq), allow_longer):
        log.info("%s: %d rows for the %d frames of %s; run again", path, len(boxes), len(seq), seq.name)
        return False
    if first_box is not None and not np.allclose(boxes[0], first_box, atol=1e-3, rtol=0):
        log.info("%s starts from %s, not from %s; run again", path, boxes[0].tolist(), first_box.tolist())
        return False
    if recorded_settings(out_dir, tracker, seq.name) != settings_of(tracker):
        log.info("%s was recorded with other settings of %s (its configuration, or the tacf or OpenCV version), or "
                 "before they were recorded; run again", path, tracker)
        return False
    return True


def pending_jobs(trackers: list[str], sequences: list[Sequence], out_dir: Path, force: bool = False,
                 start: Start = Start(), allow_longer: bool = False) -> list[Job]:
    """The (tracker, sequence) pairs without a recorded result (all of them with `force`), for runs from `start`;
    `allow_longer`: see `rows_fit`."""
    out_dir = start.directory(out_dir)
    jobs = []
    for name in trackers:
        for seq in start.sequences(sequences):
            first_box = None if start.from_first_frame else seq.gt[0]
            if force or not is_recorded(out_dir, name, seq, allow_longer and start.from_first_frame, first_box):
                jobs.append(Job(name, seq, out_dir, start))
            else:
                log.debug("%s/%s already recorded; skipped", name, seq.name)
    return jobs


# A dead worker breaks the whole pool: ProcessPoolExecutor fails every pair not done by then, not only its own.
WORKER_DIED = ("a worker process died (killed, say by the out-of-memory killer, or crashed in native code) before "
               "this pair was done")


def run_jobs(jobs: list[Job], workers: int = 1, progress: bool = True) -> list[JobOutcome]:
    """Run jobs in this process (workers <= 1) or in a pool of spawned processes, with a tqdm progress bar; the
    outcomes come in the order the jobs end. When a worker dies, the pairs it left undone run again, and only the
    pair that was running in it when it died fails (`WORKER_DIED`). OutOfRoom when a result could not be written
    for want of room: the pairs running are ended, the others not run."""
    from tqdm import tqdm

    outcomes = []
    bar = tqdm(total=len(jobs), desc="eval", unit="seq", disable=not progress or not jobs)

    def done(outcome: JobOutcome) -> None:
        bar.set_postfix_str(f"{outcome.tracker} {outcome.seq_name}")
        outcomes.append(outcome)
        bar.update()
        if outcome.no_room:
            raise OutOfRoom(outcome, len(jobs) - len(outcomes))
    try:
        if workers <= 1 or len(jobs) <= 1:
            for job in jobs:
                done(run_job(job))
        else:
            _run_in_pools(jobs, workers, done)
    finally:
        bar.close()
    return outcomes


def _run_in_pools(jobs: list[Job], workers: int, done) -> None:
    """run_jobs' pools. A pool handed each worker a pair and queued one more: of the pairs a dead worker left
    undone, those first `workers + 1` (the suspects) run again one at a time, where a worker that dies names its
    pair, then the others in a new pool."""
    remaining = jobs
    while remaining:
        undone = _run_pool(remaining, min(workers, len(remaining)), done)
        if not undone:
            return
        log.warning("a worker process died: the %d pair(s) it left undone run again", len(undone))
        suspects, remaining = undone[:workers + 1], undone[workers + 1:]
        while suspects:
            undone = _run_pool(suspects, 1, done)
            if undone:
                done(failed_outcome(undone[0], WORKER_DIED))
            suspects = undone[1:]


def _run_pool(jobs: list[Job], workers: int, done) -> list[Job]:
    """Run `jobs` in a new pool of `workers` spawned processes, passing each outcome to `done`; the jobs a dead
    worker left undone, in the order given."""
    # Ctrl-C reaches the whole process group: this process alone stops the run, ending the workers
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=signal.signal, initargs=(signal.SIGINT, signal.SIG_IGN)) as pool:
        futures = [pool.submit(run_job, job) for job in jobs]
        undone = set()
        try:
            for future in as_completed(futures):
                try:
                    done(future.result())
                except BrokenProcessPool:
                    undone.add(future)
        except BaseException:   # Ctrl-C, OutOfRoom: leaving the pool would wait for the jobs running
            _terminate_workers(pool)
            raise
    return [job for job, future in zip(jobs, futures) if future in undone]


def _terminate_workers(pool: ProcessPoolExecutor) -> None:
    """End the pool's workers in the middle of their jobs, as Python 3.14's `terminate_workers` does (which reads
    the same private `_processes`)."""
    workers = list((pool._processes or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in workers:
        process.terminate()
