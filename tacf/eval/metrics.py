"""OTB one-pass-evaluation metrics: pure, vectorised numpy over N x 4 arrays of x,y,w,h boxes.

Conventions (docs ECOSYSTEM.md 3.4, as got10k and pysot compute them):
  - overlap: boxes cover [x, x + w) x [y, y + h); IoU = intersection / union;
  - success at threshold t = fraction of frames with IoU > t, t in linspace(0, 1, 21); AUC = mean of the curve;
  - centre = xy + (wh - 1) / 2; precision at t px = fraction of frames with centre distance <= t, t = 0..50;
    the precision score is the value at 20 px;
  - a NaN prediction counts as a miss;
  - frames whose ground truth is NaN or empty (w or h <= 0), the target absent, are skipped by default
    (absent="skip"), as got10k's UAV123 experiment does. pysot (success_overlap / success_error) and the OTB /
    UAV123 MATLAB toolkit (calcSeqErrRobust + perfPlot) divide by all frames instead, an absent frame being a
    failure at every overlap threshold (IoU -1) and a hit at every distance (error -1): absent="toolkit";
    where the toolkits' own tests of a missing target differ, these numbers may too, on rare frames only: got10k
    skips only NaN rows (it scores an empty box as IoU 0); pysot's precision takes a target as absent when its
    centre is not right of and below (0, 0) rather than when its box is empty; the MATLAB toolkit when any of x, y,
    w, h is not > 0, and it replaces a NaN or empty prediction by the frame before's;
  - a lost flag: the share of failures (IoU < 0.1) it flags and of tracked frames (IoU > 0.5) it flags wrongly.
Shifting both boxes by the same offset (0- vs 1-based) changes none of these numbers.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

IOU_THRESHOLDS = np.linspace(0.0, 1.0, 21)
# A tracker's lost flag is judged against the overlap: a frame under FAILURE_IOU is a failure the flag should
# catch, a frame over TRACKED_IOU a tracked one it should leave alone; the frames between count for neither.
FAILURE_IOU, TRACKED_IOU = 0.1, 0.5
DIST_THRESHOLDS = np.arange(0, 51, dtype=np.float64)
PRECISION_AT = 20
ABSENT = ("skip", "toolkit")  # how frames without a target count: see the module docstring


def _as_boxes(boxes) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes must be N x 4 x,y,w,h, got shape {boxes.shape}")
    return boxes


def valid_mask(gt) -> np.ndarray:
    """True for ground-truth rows that are finite with w > 0 and h > 0."""
    gt = _as_boxes(gt)
    return np.isfinite(gt).all(axis=1) & (gt[:, 2] > 0) & (gt[:, 3] > 0)


def iou(pred, gt) -> np.ndarray:
    """Per-frame intersection over union of two N x 4 xywh arrays (0 where either box is empty or NaN)."""
    a, b = _as_boxes(pred), _as_boxes(gt)
    if a.shape != b.shape:
        raise ValueError(f"shape mismatch: {a.shape} vs {b.shape}")
    left = np.maximum(a[:, 0], b[:, 0])
    top = np.maximum(a[:, 1], b[:, 1])
    right = np.minimum(a[:, 0] + a[:, 2], b[:, 0] + b[:, 2])
    bottom = np.minimum(a[:, 1] + a[:, 3], b[:, 1] + b[:, 3])
    inter = np.clip(right - left, 0, None) * np.clip(bottom - top, 0, None)
    area_a = np.clip(a[:, 2], 0, None) * np.clip(a[:, 3], 0, None)
    area_b = np.clip(b[:, 2], 0, None) * np.clip(b[:, 3], 0, None)
    union = area_a + area_b - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(union > 0, inter / union, 0.0)
    return np.nan_to_num(np.clip(out, 0.0, 1.0), nan=0.0)


def box_iou(a, b) -> float:
    """IoU of one pair of (x, y, w, h) boxes, as `iou` computes it per frame."""
    return float(iou([a], [b])[0])


def center_error(pred, gt) -> np.ndarray:
    """Per-frame Euclidean distance between box centres xy + (wh - 1) / 2 (inf where a box is NaN)."""
    a, b = _as_boxes(pred), _as_boxes(gt)
    ca = a[:, :2] + (a[:, 2:] - 1) / 2
    cb = b[:, :2] + (b[:, 2:] - 1) / 2
    d = np.sqrt(np.sum((ca - cb) ** 2, axis=1))
    return np.where(np.isfinite(d), d, np.inf)


def frames_scored(gt, absent: str = "skip") -> int:
    """The frames the curves' fractions are of: those with a target (absent="skip") or all (absent="toolkit")."""
    if absent not in ABSENT:
        raise ValueError(f"absent must be one of {', '.join(ABSENT)}, got {absent!r}")
    return int(valid_mask(gt).sum()) if absent == "skip" else len(_as_boxes(gt))


def _rates(hits: np.ndarray, keep: np.ndarray, absent: str, absent_hit: bool) -> np.ndarray:
    """Per-threshold hits over the valid-gt frames as a fraction: of those frames (absent="skip"), or of all
    frames with each absent one a hit or a failure (absent="toolkit")."""
    if absent == "skip":
        return hits / keep.sum()
    if absent == "toolkit":
        return (hits + absent_hit * (~keep).sum()) / len(keep)
    raise ValueError(f"absent must be one of {', '.join(ABSENT)}, got {absent!r}")


def success_curve(pred, gt, thresholds=IOU_THRESHOLDS, absent: str = "skip") -> np.ndarray:
    """Fraction of frames with IoU > t, for each threshold t; an absent target's frames skipped or failed (see
    `absent` in the module docstring); NaN curve when no frame is valid."""
    keep = valid_mask(gt)
    if not keep.any():
        return np.full(len(thresholds), np.nan)
    ious = iou(_as_boxes(pred)[keep], _as_boxes(gt)[keep])
    return _rates((ious[:, None] > np.asarray(thresholds)[None, :]).sum(axis=0), keep, absent, False)


def precision_curve(pred, gt, thresholds=DIST_THRESHOLDS, absent: str = "skip") -> np.ndarray:
    """Fraction of frames with centre distance <= t px, for each threshold t; an absent target's frames skipped
    or hits (see `absent` in the module docstring); NaN curve when no frame is valid."""
    keep = valid_mask(gt)
    if not keep.any():
        return np.full(len(thresholds), np.nan)
    dist = center_error(_as_boxes(pred)[keep], _as_boxes(gt)[keep])
    return _rates((dist[:, None] <= np.asarray(thresholds)[None, :]).sum(axis=0), keep, absent, True)


def auc(curve) -> float:
    """Area under the success curve: the mean of its points."""
    return float(np.mean(curve))


@dataclass(frozen=True)
class Scores:
    """Scores of one sequence: AUC, precision at 20 px, both curves and the number of frames scored."""

    auc: float
    precision20: float
    success: np.ndarray
    precision: np.ndarray
    frames_scored: int


def score(pred, gt, absent: str = "skip") -> Scores:
    """All OPE scores of one predicted track against its ground truth; `absent`: see the module docstring."""
    succ = success_curve(pred, gt, absent=absent)
    prec = precision_curve(pred, gt, absent=absent)
    return Scores(auc(succ), float(prec[PRECISION_AT]), succ, prec, frames_scored(gt, absent))


def lost_flag_rates(lost, overlaps) -> dict:
    """How a per-frame lost flag matches the overlaps of the same frames: the share of frames flagged, of the
    failures flagged (IoU < FAILURE_IOU: the flag's recall), of the tracked frames flagged (IoU > TRACKED_IOU:
    false alarms) and of the flags that fell on failures (precision); NaN where a share has no frames."""
    lost, overlaps = np.asarray(lost, bool), np.asarray(overlaps, np.float64)
    failures, tracked = overlaps < FAILURE_IOU, overlaps > TRACKED_IOU

    def share(flags: np.ndarray) -> float:
        return float(flags.mean()) if len(flags) else float("nan")

    return {"frames": int(len(lost)), "failures": int(failures.sum()), "tracked": int(tracked.sum()),
            "flagged": share(lost), "failures_flagged": share(lost[failures]),
            "tracked_flagged": share(lost[tracked]), "flags_on_failures": share(failures[lost])}


def lost_flag_curve(confidence, overlaps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(thresholds, failures flagged, tracked frames flagged) when the flag is `confidence < threshold`, for
    every threshold that changes it (each confidence value, and one above them all): the trade-off a lost-flag
    threshold chooses from. NaN confidences never flag."""
    confidence, overlaps = np.asarray(confidence, np.float64), np.asarray(overlaps, np.float64)
    known = np.isfinite(confidence)
    failures = np.sort(confidence[known & (overlaps < FAILURE_IOU)])
    tracked = np.sort(confidence[known & (overlaps > TRACKED_IOU)])
    values = np.unique(confidence[known])
    thresholds = np.append(values, values[-1] + 1.0) if len(values) else np.zeros(0)

    def flagged(sorted_values: np.ndarray, total: int) -> np.ndarray:
        counts = np.searchsorted(sorted_values, thresholds, side="left")
        return counts / total if total else np.full(len(thresholds), np.nan)

    return (thresholds, flagged(failures, int((overlaps < FAILURE_IOU).sum())),
            flagged(tracked, int((overlaps > TRACKED_IOU).sum())))
