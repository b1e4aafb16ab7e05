"""Reports over a result tree: summary.json, a markdown table, success and precision plots, an overlap plot per
sequence.

summary.json shape (read by other tools; docs DESIGN.md 6):
  {"trackers": {NAME: {"auc": f, "precision20": f, "fps": f, "frames": n,
                       "sequences": {SEQ: {"auc": f, "precision20": f, "fps": f, "frames": n}}}}}
A tracker's auc and precision20 are the means over its sequences (as benchmark tables report them);
fps = frames / tracker seconds over the sequences that have timing; frames = total frames tracked.
With `tacf eval --shifts` summary.json also has "robustness", with `--tre` "temporal_robustness" (see `robustness`),
for the trackers that recorded their lost flag, "lost_flag" (see `lost_flag_summary`), and "attributes", the scores
per sequence attribute (see `attribute_scores`). "protocol" says how the frames without a target counted (see
`scoring_protocol`).
"""
from __future__ import annotations

import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import metrics
from .attributes import ATTRIBUTE_NAMES
from .datasets import Sequence
from .runner import read_confidence, read_run, result_path, rows_fit
from .text_files import drawable, write_atomically

log = logging.getLogger(__name__)

ABLATION_LABELS = {"kcc": "KCC (baseline)", "kcc+sa": "KCC + SA", "kcc+da": "KCC + DA", "kcc+ca": "KCC + CA",
                   "tacf-authors": "TACF (SA + DA + CA)", "tacf": "TACF, the paper's values (the default)"}


# One colour per tracker, in report order, shared by the per-sequence plots and the comparison videos: the first
# ten of matplotlib's default cycle (tab10).
TRACKER_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                   "#bcbd22", "#17becf")


def counted(count: int, noun: str) -> str:
    """'1 sequence', '2 sequences' (the logs and titles said "1 sequences")."""
    return f"{count} {noun}" + ("" if count == 1 else "s")


def tracker_colour(index: int) -> str:
    return TRACKER_COLOURS[index % len(TRACKER_COLOURS)]


def _line_style(index: int) -> dict:
    """The i-th tracker's colour, and past ten trackers a dash style that tells repeated colours apart."""
    return {"color": tracker_colour(index), "linestyle": ("-", "--", ":")[index // len(TRACKER_COLOURS) % 3]}


def _save_figure(fig, path: Path) -> None:
    """`fig` as a PNG at `path`, written whole or not at all (write_atomically), and closed."""
    import matplotlib.pyplot as plt

    png = io.BytesIO()
    fig.savefig(png, format="png")
    plt.close(fig)
    write_atomically(path, png.getvalue())


@dataclass
class TrackerReport:
    """Scores of one tracker: per-sequence entries plus the mean curves for the plots, and the boxes scored
    (0-based, per sequence name) for the per-sequence plots and videos."""

    name: str
    sequences: dict = field(default_factory=dict)
    success: list = field(default_factory=list)
    precision: list = field(default_factory=list)
    boxes: dict = field(default_factory=dict)
    # (ok, pme, IoU) of the frames after the first with a target, per sequence whose confidence was recorded
    flag_frames: list = field(default_factory=list)
    frames: int = 0
    # fps counts only the sequences with timing: imported results may lack it for some
    timed_frames: int = 0
    seconds: float = 0.0

    def entry(self) -> dict:
        aucs = [s["auc"] for s in self.sequences.values() if np.isfinite(s["auc"])]
        precs = [s["precision20"] for s in self.sequences.values() if np.isfinite(s["precision20"])]
        return {"auc": float(np.mean(aucs)) if aucs else float("nan"),
                "precision20": float(np.mean(precs)) if precs else float("nan"),
                "fps": self.timed_frames / self.seconds if self.seconds > 0 else float("nan"),
                "frames": int(self.frames),
                "sequences": self.sequences}

    def mean_curves(self, names=None) -> tuple[np.ndarray, np.ndarray]:
        """Mean success and precision curves over the sequences scored, or over those of them in `names`."""
        picked = [i for i, name in enumerate(self.sequences) if names is None or name in names]
        return (np.nanmean([self.success[i] for i in picked], axis=0),
                np.nanmean([self.precision[i] for i in picked], axis=0))


def score_tracker(out_dir: Path, tracker: str, sequences: list[Sequence], absent: str = "skip",
                  allow_longer: bool = False) -> TrackerReport:
    """Score every recorded result of `tracker` in the result tree `out_dir` against the sequences' ground truth
    (`absent`: see metrics; `allow_longer`: see runner.rows_fit)."""
    runs, confidences = {}, {}
    for seq in sequences:
        if not result_path(out_dir, tracker, seq.name).is_file():
            log.warning("%s: no result for %s; left out of the summary", tracker, seq.name)
            continue
        boxes, times = read_run(out_dir, tracker, seq.name)
        if not rows_fit(len(boxes), len(seq), allow_longer):
            log.warning("%s/%s: %d result rows for %d frames; left out", tracker, seq.name, len(boxes), len(seq))
            continue
        runs[seq.name] = boxes[:len(seq)], times[:len(seq)]
        confidence = read_confidence(out_dir, tracker, seq.name)
        if confidence is not None and len(confidence[0]) == len(boxes):
            confidences[seq.name] = tuple(column[:len(seq)] for column in confidence)
    return score_runs(tracker, sequences, runs, confidences, absent)


def score_runs(name: str, sequences: list[Sequence], runs: dict[str, tuple[np.ndarray, np.ndarray]],
               confidences: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
               absent: str = "skip") -> TrackerReport:
    """Score runs {sequence name: (0-based boxes, seconds per frame)}, one box per frame of the sequence, and
    the lost flags of those with confidences {sequence name: (pme, ok)}; `absent`: see metrics."""
    rep = TrackerReport(name)
    for seq in sequences:
        if seq.name not in runs:
            continue
        boxes, times = runs[seq.name]
        s = metrics.score(boxes, seq.gt, absent)
        seconds = float(np.nansum(times))
        rep.sequences[seq.name] = {"auc": s.auc, "precision20": s.precision20,
                                   "fps": len(boxes) / seconds if seconds > 0 else float("nan"),
                                   "frames": len(boxes)}
        rep.success.append(s.success)
        rep.precision.append(s.precision)
        rep.boxes[seq.name] = boxes
        if confidences and seq.name in confidences:
            pme, ok = confidences[seq.name]
            judged = metrics.valid_mask(seq.gt)
            judged[0] = False  # the init frame has no flag
            rep.flag_frames.append((ok[judged], pme[judged], metrics.iou(boxes, seq.gt)[judged]))
        rep.frames += len(boxes)
        if np.isfinite(seconds) and seconds > 0:
            rep.timed_frames += len(boxes)
            rep.seconds += seconds
    return rep


def summarize(out_dir: Path, trackers: list[str], sequences: list[Sequence],
              imported: dict[str, dict] | None = None, absent: str = "skip",
              allow_longer: bool = False) -> tuple[dict, list[TrackerReport]]:
    """(summary dict in the summary.json shape, the per-tracker reports): the trackers' results recorded in
    `out_dir`, then the imported runs {name: {sequence name: (boxes, times)}} (`tacf eval --results`), the frames
    without a target counted as `absent` says (see metrics); `allow_longer`: see runner.rows_fit."""
    reports = [score_tracker(out_dir, t, sequences, absent, allow_longer) for t in trackers]
    reports += [score_runs(name, sequences, runs, absent=absent) for name, runs in (imported or {}).items()]
    return {"trackers": {r.name: r.entry() for r in reports}, "protocol": scoring_protocol(sequences, absent)}, reports


def scoring_protocol(sequences: list[Sequence], absent: str) -> dict:
    """summary.json's "protocol": how the frames without a target (NaN or empty ground truth) counted, and how many
    of the sequences' frames they are."""
    return {"absent": absent, "absent_frames": int(sum((~metrics.valid_mask(s.gt)).sum() for s in sequences)),
            "frames": int(sum(len(s) for s in sequences))}


ABSENT_TEXT = {"skip": "left out of the scores, as got10k's UAV123 experiment does (`--absent toolkit` counts them "
                       "as pysot and the OTB / UAV123 MATLAB toolkit do)",
               "toolkit": "counted as pysot and the OTB / UAV123 MATLAB toolkit count them (`--absent toolkit`): a "
                          "failure at every overlap threshold, a hit at every distance"}


def protocol_line(result: dict) -> str:
    """summary.json's "protocol" as a sentence."""
    return (f"Frames without a target (NaN or empty ground truth): {result['absent_frames']} of {result['frames']}, "
            f"{ABSENT_TEXT[result['absent']]}.")


def _pooled_flag_frames(r: TrackerReport) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ok, pme, IoU) over all of a tracker's judged frames."""
    return tuple(np.concatenate(column) for column in zip(*r.flag_frames))


def lost_flag_summary(reports: list[TrackerReport]) -> dict:
    """summary.json's "lost_flag": per tracker that recorded its flags, metrics.lost_flag_rates of `not ok` over
    all its frames after the first (pooled over the sequences), with the IoU bounds they were judged by."""
    trackers = {}
    for r in reports:
        if r.flag_frames:
            ok, _, overlaps = _pooled_flag_frames(r)
            trackers[r.name] = metrics.lost_flag_rates(~ok, overlaps)
    return {"failure_iou": metrics.FAILURE_IOU, "tracked_iou": metrics.TRACKED_IOU, "trackers": trackers}


def lost_flag_table(result: dict) -> str:
    """summary.json's "lost_flag" as markdown."""
    if not result.get("trackers"):
        return ""

    def percent(v: float) -> str:
        return "n/a" if v is None or not np.isfinite(v) else f"{100 * v:.1f} %"

    lines = [f"Lost flag (ok = false) against the overlap, on the frames after the first: a failure is IoU < "
             f"{result['failure_iou']:g}, a tracked frame IoU > {result['tracked_iou']:g}:", "",
             "| tracker | frames | flagged | failures flagged | tracked frames flagged | flags on failures |",
             "|---|---|---|---|---|---|"]
    for name, t in result["trackers"].items():
        lines.append(f"| {name} | {t['frames']} | {percent(t['flagged'])} | {percent(t['failures_flagged'])} of "
                     f"{t['failures']} | {percent(t['tracked_flagged'])} of {t['tracked']} | "
                     f"{percent(t['flags_on_failures'])} |")
    return "\n".join(lines) + "\n"


def attribute_scores(summary: dict, attributes: dict[str, frozenset[str]], source: str) -> dict:
    """summary.json's "attributes": for each attribute some sequence has, its sequences and every tracker's mean
    AUC and precision over those it scored, as the benchmarks' per-attribute plots average them:
    {"source": how the attributes were found, "attributes": {ATTR: {"name": f, "sequences": [SEQ, ...],
    "trackers": {NAME: {"auc": f, "precision20": f, "sequences": n}}}}}"""
    present = {a for labels in attributes.values() for a in labels}
    known = [a for a in ATTRIBUTE_NAMES if a in present]
    result = {"source": source, "attributes": {}}
    for attribute in known + sorted(present - set(known)):
        names = sorted(name for name, labels in attributes.items() if attribute in labels)
        trackers = {}
        for tracker, entry in summary["trackers"].items():
            scored = [entry["sequences"][name] for name in names if name in entry["sequences"]]
            trackers[tracker] = {key: float(np.mean([s[key] for s in scored])) if scored else float("nan")
                                 for key in ("auc", "precision20")}
            trackers[tracker]["sequences"] = len(scored)
        result["attributes"][attribute] = {"name": ATTRIBUTE_NAMES.get(attribute, attribute), "sequences": names,
                                           "trackers": trackers}
    return result


ATTRIBUTE_SOURCES = {"table": "from the --attributes table", "dataset": "the benchmark's own labels",
                     "derived": "derived from the ground truth by UAV123's definitions"}


def attribute_table(summary: dict) -> str:
    """summary.json's "attributes" as markdown: one row per attribute, one AUC column per tracker (ranked)."""
    result = summary.get("attributes", {})
    if not result.get("attributes"):
        return ""
    ranked = [name for name, _ in _ranked(summary)]
    lines = [f"Success AUC per attribute ({ATTRIBUTE_SOURCES[result['source']]}):", "",
             "| attribute | sequences | " + " | ".join(ranked) + " |", "|---|---|" + "---|" * len(ranked)]
    for attribute, a in result["attributes"].items():
        cells = [_f(a["trackers"][name]["auc"]) for name in ranked]
        lines.append(f"| {attribute} ({a['name']}) | {len(a['sequences'])} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_attributes(reports: list[TrackerReport], result: dict, out_dir: Path) -> Path:
    """attributes_plot.png: a success plot per attribute, each tracker's mean curve over that attribute's
    sequences, best first in each legend, as the benchmark papers draw them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    attributes = result["attributes"]
    cols = math.ceil(math.sqrt(len(attributes)))
    rows = math.ceil(len(attributes) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows), dpi=100, squeeze=False)
    xs = metrics.IOU_THRESHOLDS
    for ax, (attribute, a) in zip(axes.flat, attributes.items()):
        curves = []
        for i, r in enumerate(reports):
            names = set(a["sequences"]) & set(r.sequences)
            if names:
                success, _ = r.mean_curves(names)
                curves.append((float(np.mean(success)), i, r.name, success))
        for auc, i, name, success in sorted(curves, key=lambda c: -c[0]):
            ax.plot(xs, success, label=f"{name} [{auc:.3f}]", linewidth=1.5, **_line_style(i))
        ax.set(title=f"{a['name']} ({attribute}, {counted(len(a['sequences']), 'sequence')})",
               xlabel="Overlap threshold",
               ylabel="Success rate", xlim=(xs[0], xs[-1]), ylim=(0, 1.01))
        ax.grid(alpha=0.3)
        if curves:
            ax.legend(loc="upper right", fontsize=7)
    for ax in axes.flat[len(attributes):]:
        ax.axis("off")
    fig.suptitle(f"Success plots of OPE per attribute ({ATTRIBUTE_SOURCES[result['source']]})")
    fig.tight_layout()
    path = Path(out_dir) / "attributes_plot.png"
    _save_figure(fig, path)
    return path


def _ranked(summary: dict) -> list[tuple[str, dict]]:
    return sorted(summary["trackers"].items(), key=lambda kv: -np.nan_to_num(kv[1]["auc"], nan=-1.0))


def _f(v: float, digits: int = 3) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def markdown_table(summary: dict) -> str:
    """Trackers sorted by AUC, then the AUC of every sequence."""
    lines = ["| tracker | AUC | precision@20 | FPS | frames | sequences |", "|---|---|---|---|---|---|"]
    ranked = _ranked(summary)
    for name, t in ranked:
        lines.append(f"| {name} | {_f(t['auc'])} | {_f(t['precision20'])} | {_f(t['fps'], 1)} | {t['frames']} "
                     f"| {len(t['sequences'])} |")
    if "protocol" in summary:
        lines += ["", protocol_line(summary["protocol"])]
    per_sequence = {name: {s: scores["auc"] for s, scores in t["sequences"].items()} for name, t in ranked}
    if any(per_sequence.values()):
        lines += ["", per_sequence_table("Success AUC per sequence:", per_sequence)]
    return "\n".join(lines) + "\n"


def per_sequence_table(title: str, columns: dict[str, dict[str, float]]) -> str:
    """A markdown table of one value per sequence (rows, sorted) and tracker (columns {tracker: {sequence: v}},
    in their order); "-" where a tracker has no value. No final newline: it is a part of a report."""
    names = sorted({s for values in columns.values() for s in values})
    lines = [title, "", "| sequence | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
    for s in names:
        lines.append(f"| {s} | " + " | ".join(_f(v[s]) if s in v else "-" for v in columns.values()) + " |")
    return "\n".join(lines)


# A bootstrap over fewer sequences has too few distinct resamples for its percentiles to mean anything: over one
# sequence it is that sequence's value twice, an interval of no width that would read as a sure difference.
MIN_SEQUENCES_FOR_INTERVAL = 5


def bootstrap_indices(count: int, resamples: int = 10000) -> np.ndarray | None:
    """(resamples, count) sequence indices drawn with replacement, with a fixed seed: every report resamples alike;
    None for fewer than MIN_SEQUENCES_FOR_INTERVAL sequences (no interval is given then)."""
    if count < MIN_SEQUENCES_FOR_INTERVAL:
        return None
    return np.random.default_rng(0).integers(0, count, (resamples, count))


def percentile_interval(resampled: np.ndarray | None) -> tuple[float, float]:
    """The 95 % interval of resampled statistics; NaN, NaN without resamples (too few sequences)."""
    if resampled is None:
        return float("nan"), float("nan")
    low, high = np.percentile(resampled, [2.5, 97.5])
    return float(low), float(high)


def interval_text(low: float, high: float, fmt: str = "+.3f") -> str:
    """"(low to high)", or why there is none."""
    if not (np.isfinite(low) and np.isfinite(high)):
        return f"(no interval: under {MIN_SEQUENCES_FOR_INTERVAL} sequences)"
    return f"({low:{fmt}} to {high:{fmt}})"


def relative_gain(aucs, base_aucs, resamples: int = 10000) -> tuple[float, float, float]:
    """mean(aucs) / mean(base_aucs) - 1 over paired per-sequence AUCs (the paper's relative gain), and its 95 %
    bootstrap interval over the sequences (NaN under MIN_SEQUENCES_FOR_INTERVAL sequences)."""
    aucs, base = np.asarray(aucs, float), np.asarray(base_aucs, float)
    picks = bootstrap_indices(len(aucs), resamples)
    resampled = None
    if picks is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            resampled = aucs[picks].sum(axis=1) / base[picks].sum(axis=1) - 1
    return (float(aucs.sum() / base.sum() - 1), *percentile_interval(resampled))


def ablation_table(summary: dict) -> str:
    """The paper's ablation rows (KCC, +SA, +DA, +CA, all three) and the default tacf, then any other tracker of the
    summary (imported results), with the AUC gain over KCC, also relative, with the relative gain's 95 % bootstrap
    interval over the sequences both scored."""
    trackers = summary["trackers"]
    kcc = trackers.get("kcc", {})
    lines = ["| variant | tracker | AUC | gain over KCC | relative gain (95 % interval) | precision@20 | FPS |",
             "|---|---|---|---|---|---|---|"]
    rows = [n for n in ABLATION_LABELS if n in trackers] + [n for n in trackers if n not in ABLATION_LABELS]
    for name in rows:
        label, t = ABLATION_LABELS.get(name, "imported results"), trackers[name]
        gain = t["auc"] - kcc.get("auc", float("nan"))
        names = sorted(set(t["sequences"]) & set(kcc.get("sequences", {})))
        relative = "-"
        if names:
            mean, low, high = relative_gain([t["sequences"][n]["auc"] for n in names],
                                            [kcc["sequences"][n]["auc"] for n in names])
            relative = f"{mean:+.1%} {interval_text(low, high, '+.1%')}"
        lines.append(f"| {label} | {name} | {_f(t['auc'])} | {'+' if gain >= 0 else ''}{_f(gain)} | {relative} "
                     f"| {_f(t['precision20'])} | {_f(t['fps'], 1)} |")
    return "\n".join(lines) + "\n"


def robustness(per_start: dict[str, dict], trackers: list[str], protocol: str = "shifts",
               resamples: int = 10000, frames_scored: dict[str, dict[str, int]] | None = None) -> dict:
    """How far each tracker's mean AUC moves over several starts of the same runs (the first box moved by a few
    pixels, protocol "shifts"; later first frames, protocol "tre"), and whether the other trackers' differences to
    the first tracker stand out of that.

    per_start: {start label: summary dict of the runs started there}, the given start first; the sequences scored
    in every start count. Per tracker: the mean AUC of each start, their mean, min and max. Per later tracker: its
    AUC minus the first tracker's, per sequence averaged over the starts, then over the sequences, with a 95 %
    bootstrap interval over the sequences (fixed seed; NaN under MIN_SEQUENCES_FOR_INTERVAL sequences): an interval
    that holds 0 means the sequences cannot tell the two apart. "per_sequence" holds each sequence's AUC averaged
    over the starts: where the differences are.

    With frames_scored {start label: {sequence name: frames scored}} (metrics.frames_scored), each tracker also
    gets "otb_pooled", the AUC and precision@20 as OTB's toolkit computes TRE (genPerfMat): per sequence, the hits
    of all its starts over all the frames they scored, so that a short late start weighs less than the mean over
    the starts weighs it; then the mean over the sequences.
    """
    starts = list(per_start)
    sequence_sets = [set(summary["trackers"][t]["sequences"]) for summary in per_start.values() for t in trackers]
    names = sorted(set.intersection(*sequence_sets)) if sequence_sets else []

    def per_sequence(t: str, key: str) -> np.ndarray:  # (starts, sequences)
        return np.array([[per_start[start]["trackers"][t]["sequences"][n][key] for n in names] for start in starts])

    aucs = {t: per_sequence(t, "auc") for t in trackers}
    result = {"protocol": protocol, "starts": starts, "sequences": len(names), "trackers": {}}
    if not names:
        return result
    first = trackers[0]
    resampled = bootstrap_indices(len(names), resamples)
    for t in trackers:
        per_start_auc = aucs[t].mean(axis=1)
        entry = {"auc_per_start": per_start_auc.tolist(), "mean": float(per_start_auc.mean()),
                 "min": float(per_start_auc.min()), "max": float(per_start_auc.max()),
                 "per_sequence": dict(zip(names, aucs[t].mean(axis=0).tolist()))}
        if t != first:
            difference = (aucs[t] - aucs[first]).mean(axis=0)
            low, high = percentile_interval(None if resampled is None else difference[resampled].mean(axis=1))
            entry["difference"] = {"to": first, "mean": float(difference.mean()), "ci95": [low, high]}
        if frames_scored is not None:
            weights = np.array([[frames_scored[start][n] for n in names] for start in starts], float)
            entry["otb_pooled"] = {key: _pooled(per_sequence(t, key), weights) for key in ("auc", "precision20")}
        result["trackers"][t] = entry
    return result


def _pooled(values: np.ndarray, weights: np.ndarray) -> float:
    """Mean over the sequences of each sequence's per-start fractions (starts x sequences) pooled over the frames
    they are of: the hits over all its starts divided by all its frames scored."""
    hits = np.where(weights > 0, values * weights, 0.0)  # a start without a frame scored has a NaN score
    return float(np.mean(hits.sum(axis=0) / weights.sum(axis=0)))


def robustness_table(result: dict) -> str:
    """The robustness dict as markdown: one row per tracker."""
    trackers = result["trackers"]
    if not trackers:
        return ""
    first = next(iter(trackers))
    starts = ", ".join(f"({start})" for start in result["starts"])
    if result["protocol"] == "tre":
        title = f"Temporal robustness: runs started at {starts} of each sequence"
    else:
        title = f"Robustness: first box moved by (dx,dy) = {starts} pixels"
    pooled = all("otb_pooled" in t for t in trackers.values())
    lines = [f"{title}; {counted(result['sequences'], 'sequence')}:", "",
             f"| tracker | AUC, one pass | mean over the starts | min - max | difference to {first} "
             "(95 % interval over sequences) |" + (" OTB's TRE, pooled: AUC / precision@20 |" if pooled else ""),
             "|---|---|---|---|---|" + ("---|" if pooled else "")]
    for name, t in trackers.items():
        difference = t.get("difference")
        cell = "-" if difference is None else f"{difference['mean']:+.3f} {interval_text(*difference['ci95'])}"
        lines.append(f"| {name} | {_f(t['auc_per_start'][0])} | {_f(t['mean'])} | {_f(t['min'])} - {_f(t['max'])} "
                     f"| {cell} |" + (f" {_f(t['otb_pooled']['auc'])} / {_f(t['otb_pooled']['precision20'])} |"
                                      if pooled else ""))
    if pooled:
        lines += ["", "The mean over the starts weighs every start alike; OTB's TRE (genPerfMat) pools each "
                      "sequence's frames over its starts, so that a short late start weighs less."]
    title = f"Success AUC per sequence, the mean over the {len(result['starts'])} starts:"
    lines += ["", per_sequence_table(title, {name: t["per_sequence"] for name, t in trackers.items()})]
    return "\n".join(lines) + "\n"


def plot_curves(reports: list[TrackerReport], out_dir: Path) -> list[Path]:
    """success_plot.png and precision_plot.png: one mean curve per tracker, best first in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    specs = [("success_plot.png", "Success plot of OPE", "Overlap threshold", "Success rate",
              metrics.IOU_THRESHOLDS, 0, lambda s, p: float(np.mean(s)), "AUC"),
             ("precision_plot.png", "Precision plot of OPE", "Location error threshold (px)", "Precision",
              metrics.DIST_THRESHOLDS, 1, lambda s, p: float(p[metrics.PRECISION_AT]), "P@20")]
    for fname, title, xlabel, ylabel, xs, which, key, label in specs:
        curves = []
        for i, r in enumerate(reports):
            if r.success:
                succ, prec = r.mean_curves()
                curves.append((key(succ, prec), i, r.name, (succ, prec)[which]))
        curves.sort(key=lambda c: -c[0])
        fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
        for value, i, name, ys in curves:  # each tracker keeps its style in every picture of the run
            ax.plot(xs, ys, label=f"{name} [{label} {value:.3f}]", linewidth=1.8, **_line_style(i))
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel, xlim=(xs[0], xs[-1]), ylim=(0, 1.01))
        ax.grid(alpha=0.3)
        if curves:
            ax.legend(loc="upper right" if which == 0 else "lower right", fontsize=8)
        fig.tight_layout()
        path = Path(out_dir) / fname
        _save_figure(fig, path)
        paths.append(path)
    return paths


def plot_overlaps(reports: list[TrackerReport], sequences: list[Sequence], out_dir: Path) -> list[Path]:
    """overlap/<seq>.png: every tracker's IoU with the ground truth frame by frame (gaps where the target is
    absent), which shows where and how each one lost the target; the legend gives the sequence's AUC."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for seq in sequences:
        scored = [(i, r) for i, r in enumerate(reports) if seq.name in r.boxes]
        if not scored:
            continue
        present = metrics.valid_mask(seq.gt)
        frames = np.arange(1, len(seq) + 1)
        fig, ax = plt.subplots(figsize=(8, 3), dpi=100)
        for i, r in scored:
            overlap = np.where(present, metrics.iou(r.boxes[seq.name], seq.gt), np.nan)
            ax.plot(frames, overlap, linewidth=1.4, label=f"{r.name} [AUC {r.sequences[seq.name]['auc']:.3f}]",
                    **_line_style(i))
        ax.set(title=f"{drawable(seq.name)}: overlap with the ground truth", xlabel="frame", ylabel="IoU",
               xlim=(1, max(len(seq), 2)), ylim=(0, 1.01))
        ax.grid(alpha=0.3)
        ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
        fig.tight_layout()
        path = Path(out_dir) / "overlap" / f"{seq.name}.png"
        _save_figure(fig, path)
        paths.append(path)
    return paths


def plot_lost_flags(reports: list[TrackerReport], lost_flag: dict, out_dir: Path) -> Path:
    """lost_flag_plot.png: for every tracker of `lost_flag` (summary.json's), the share of failures it flags
    against the share of tracked frames it flags wrongly (a dot), and for those with a PME, the curve of every
    PME threshold the flag could use instead: how much warning a lost flag can give, and at what cost."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
    for i, r in enumerate(reports):
        if r.name not in lost_flag["trackers"]:
            continue
        _, pme, overlaps = _pooled_flag_frames(r)
        rates = lost_flag["trackers"][r.name]
        style = _line_style(i)
        if np.isfinite(pme).any():
            _, failures_flagged, tracked_flagged = metrics.lost_flag_curve(pme, overlaps)
            ax.plot(tracked_flagged, failures_flagged, linewidth=1.4, label=f"{r.name}: PME under a threshold",
                    **style)
        ax.plot([rates["tracked_flagged"]], [rates["failures_flagged"]], "o", color=style["color"], markersize=7,
                label=f"{r.name}: its lost flag")
    ax.set(title="Lost flag: failures caught against false alarms",
           xlabel=f"tracked frames flagged (IoU > {metrics.TRACKED_IOU:g})",
           ylabel=f"failures flagged (IoU < {metrics.FAILURE_IOU:g})", ylim=(0, 1.01))
    # A useful flag lives in the first per cent of false alarms: linear up to 0.01, logarithmic beyond.
    ax.set_xscale("symlog", linthresh=0.01, linscale=1.0)
    ax.set_xlim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    path = Path(out_dir) / "lost_flag_plot.png"
    _save_figure(fig, path)
    return path


ROBUSTNESS_KEYS = {"shifts": "robustness", "tre": "temporal_robustness"}  # protocol: its summary.json key


def analysis_tables(summary: dict) -> str:
    """The robustness, lost-flag and attribute tables a summary holds, each after a blank line; empty when it holds
    none."""
    tables = [robustness_table(summary[key]) for key in ROBUSTNESS_KEYS.values()
              if summary.get(key, {}).get("trackers")]
    tables += [lost_flag_table(summary.get("lost_flag", {})), attribute_table(summary)]
    return "".join("\n" + table for table in tables if table)


def plot_robustness(result: dict, out_dir: Path) -> Path:
    """<summary key>_plot.png (robustness_plot.png, temporal_robustness_plot.png): each tracker's mean AUC from
    every start (dots; the one-pass start ringed) and their mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    trackers = result["trackers"]
    # 6 inches at least: narrower, the title and the caption under the axis were cut at one or two trackers
    fig, ax = plt.subplots(figsize=(max(1.2 * len(trackers) + 2.5, 6.0), 4), dpi=100)
    for x, t in enumerate(trackers.values()):
        aucs = np.asarray(t["auc_per_start"])
        spread = np.linspace(-0.15, 0.15, len(aucs))
        ax.scatter(x + spread, aucs, s=18, color="tab:blue", alpha=0.7)
        ax.scatter([x + spread[0]], aucs[:1], s=70, facecolors="none", edgecolors="tab:red")
        ax.hlines(t["mean"], x - 0.3, x + 0.3, color="black", linewidth=2)
    ax.set_xticks(range(len(trackers)), list(trackers), rotation=20)
    starts = "starting frames" if result["protocol"] == "tre" else "starting boxes"
    ax.set(title=f"Mean AUC from {len(result['starts'])} {starts} ({counted(result['sequences'], 'sequence')})",
           ylabel="Success AUC", xlabel="dots: one start each (ringed: the one-pass start); bar: their mean")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    path = Path(out_dir) / f"{ROBUSTNESS_KEYS[result['protocol']]}_plot.png"
    _save_figure(fig, path)
    return path


def strict_json(obj) -> str:
    """`obj` as indented JSON, NaN and infinite floats as null: strict readers (jq, JSON.parse) refuse NaN."""
    return json.dumps(_finite(obj), indent=2, allow_nan=False) + "\n"


def _finite(obj):
    """NaN/inf floats become null so that strict JSON readers accept the file."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_reports(out_dir: Path, summary: dict, reports: list[TrackerReport],
                  sequences: list[Sequence]) -> dict[str, Path]:
    """summary.json, summary.md, the two plots, one overlap plot per sequence and, with a robustness, lost-flag or
    attribute entry, its plot, in `out_dir`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    js = out_dir / "summary.json"
    write_atomically(js, strict_json(summary))
    md = out_dir / "summary.md"
    write_atomically(md, markdown_table(summary) + analysis_tables(summary))
    success, precision = plot_curves(reports, out_dir)
    plot_overlaps(reports, sequences, out_dir)
    if summary.get("lost_flag", {}).get("trackers"):
        paths["lost_flag_plot"] = plot_lost_flags(reports, summary["lost_flag"], out_dir)
    if summary.get("attributes", {}).get("attributes"):
        paths["attributes_plot"] = plot_attributes(reports, summary["attributes"], out_dir)
    paths.update({"json": js, "markdown": md, "success_plot": success, "precision_plot": precision,
                  "overlap_plots": out_dir / "overlap"})
    for key in ROBUSTNESS_KEYS.values():
        if summary.get(key, {}).get("trackers"):
            paths[f"{key}_plot"] = plot_robustness(summary[key], out_dir)
    return paths
