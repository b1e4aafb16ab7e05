"""OPE metrics: hand-computed cases, NaN handling, and agreement with got10k's formulas (written here as an oracle)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tacf.eval import metrics


# --- got10k oracle (independent re-statement of got10k.utils.metrics + ExperimentOTB._calc_curves) ----------
def got10k_rect_iou(r1, r2):
    x1 = np.maximum(r1[:, 0], r2[:, 0])
    y1 = np.maximum(r1[:, 1], r2[:, 1])
    x2 = np.minimum(r1[:, 0] + r1[:, 2], r2[:, 0] + r2[:, 2])
    y2 = np.minimum(r1[:, 1] + r1[:, 3], r2[:, 1] + r2[:, 3])
    w, h = np.maximum(x2 - x1, 0), np.maximum(y2 - y1, 0)
    inter = w * h
    union = r1[:, 2] * r1[:, 3] + r2[:, 2] * r2[:, 3] - inter
    return np.clip(inter / (union + np.finfo(float).eps), 0.0, 1.0)


def got10k_center_error(r1, r2):
    c1 = r1[:, :2] + (r1[:, 2:] - 1) / 2
    c2 = r2[:, :2] + (r2[:, 2:] - 1) / 2
    return np.sqrt(np.sum((c1 - c2) ** 2, axis=1))


def got10k_scores(boxes, anno):
    ious, ce = got10k_rect_iou(boxes, anno), got10k_center_error(boxes, anno)
    succ = np.mean(ious[:, None] > np.linspace(0, 1, 21)[None, :], axis=0)
    prec = np.mean(ce[:, None] <= np.arange(0, 51)[None, :], axis=0)
    return np.mean(succ), prec[20], succ, prec


# --- hand-computed cases ----------------------------------------------------------------------------------
def test_iou_hand_cases():
    gt = np.array([[0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10]], float)
    pred = np.array([[0, 0, 10, 10],     # identical -> 1
                     [5, 0, 10, 10],     # half overlap: 50 / 150
                     [20, 20, 5, 5],     # disjoint -> 0
                     [0, 0, 5, 5]], float)  # inside: 25 / 100
    np.testing.assert_allclose(metrics.iou(pred, gt), [1.0, 1 / 3, 0.0, 0.25])


def test_iou_touching_edges_is_zero_and_nan_prediction_is_miss():
    gt = np.array([[0, 0, 10, 10], [0, 0, 10, 10]], float)
    pred = np.array([[10, 0, 10, 10], [np.nan] * 4])
    np.testing.assert_array_equal(metrics.iou(pred, gt), [0.0, 0.0])
    assert np.isinf(metrics.center_error(pred, gt)[1])


def test_center_error_uses_matlab_centre():
    gt = np.array([[0, 0, 11, 11]], float)     # centre 5,5
    pred = np.array([[3, 4, 1, 1]], float)     # centre 3,4
    np.testing.assert_allclose(metrics.center_error(pred, gt), [np.hypot(2, 1)])


def test_success_curve_strict_threshold_and_auc():
    gt = np.tile([0, 0, 10, 10], (2, 1)).astype(float)
    pred = np.array([[0, 0, 10, 10], [5, 0, 10, 10]], float)   # IoU 1 and 1/3
    curve = metrics.success_curve(pred, gt)
    thr = np.linspace(0, 1, 21)
    expected = ((1.0 > thr).astype(float) + (1 / 3 > thr)) / 2
    np.testing.assert_allclose(curve, expected)
    assert curve[0] == 1.0 and curve[-1] == 0.0     # IoU 1 is not > 1
    # frame 1 passes 20 thresholds (0 .. 0.95), frame 2 passes 7 (0 .. 0.30): (20 + 7) / 2 / 21
    assert metrics.auc(curve) == pytest.approx(27 / 42)


def test_precision_curve_inclusive_threshold():
    gt = np.tile([0, 0, 10, 10], (3, 1)).astype(float)
    pred = gt + [[0, 0, 0, 0], [20, 0, 0, 0], [30, 40, 0, 0]]    # distances 0, 20, 50
    curve = metrics.precision_curve(pred, gt)
    assert curve[0] == pytest.approx(1 / 3)
    assert curve[19] == pytest.approx(1 / 3)
    assert curve[20] == pytest.approx(2 / 3)     # 20 <= 20 counts
    assert curve[50] == pytest.approx(1.0)
    assert metrics.score(pred, gt).precision20 == pytest.approx(2 / 3)


def test_nan_and_empty_ground_truth_frames_are_skipped():
    gt = np.array([[0, 0, 10, 10], [np.nan] * 4, [0, 0, 0, 10], [0, 0, 10, 0], [0, 0, 10, 10]], float)
    pred = np.array([[0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10], [50, 50, 10, 10]], float)
    s = metrics.score(pred, gt)
    assert s.frames_scored == 2
    assert s.success[0] == pytest.approx(0.5)
    assert s.precision20 == pytest.approx(0.5)
    assert np.isnan(metrics.score(pred[1:3], gt[1:3]).auc)


def test_absent_frames_skipped_by_default_or_counted_as_the_matlab_toolkit_and_pysot_count_them():
    gt = np.tile([20.0, 20.0, 10.0, 10.0], (10, 1))
    gt[[2, 3, 6, 9]] = np.nan                                 # 4 of 10 frames without a target
    perfect = np.where(np.isnan(gt), 0.0, gt)                 # whatever a tracker says there
    far = perfect + [100, 0, 0, 0]
    skip, toolkit = metrics.score(perfect, gt), metrics.score(perfect, gt, absent="toolkit")
    curve = np.r_[np.ones(20), 0.0]                           # IoU 1 passes every threshold but 1
    np.testing.assert_allclose(skip.success, curve)
    np.testing.assert_allclose(toolkit.success, 0.6 * curve)  # absent: IoU -1, a failure at every threshold
    assert skip.auc == pytest.approx(20 / 21) and toolkit.auc == pytest.approx(0.6 * 20 / 21)
    assert skip.precision20 == toolkit.precision20 == 1.0     # absent: error -1, a hit at every distance
    assert metrics.score(far, gt).precision20 == 0.0
    assert metrics.score(far, gt, absent="toolkit").precision20 == pytest.approx(0.4)
    np.testing.assert_allclose(metrics.precision_curve(far, gt, absent="toolkit"), 0.4)
    with pytest.raises(ValueError, match="skip, toolkit"):
        metrics.score(perfect, gt, absent="matlab")


def test_shape_errors():
    with pytest.raises(ValueError):
        metrics.iou(np.zeros((3, 4)), np.zeros((2, 4)))
    with pytest.raises(ValueError):
        metrics.success_curve(np.zeros((3, 3)), np.zeros((3, 3)))


# --- agreement with got10k ------------------------------------------------------------------------------
box = st.tuples(st.floats(-50, 500), st.floats(-50, 500), st.floats(1, 200), st.floats(1, 200))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(box, box), min_size=1, max_size=40))
def test_matches_got10k_formulas(pairs):
    pred = np.array([p for p, _ in pairs], float)
    gt = np.array([g for _, g in pairs], float)
    auc, p20, succ, prec = got10k_scores(pred, gt)
    # got10k divides by union + eps, so an IoU within float noise of a threshold (hypothesis finds exact 0.5s)
    # may fall on either side of it there and here: the curves are compared away from such ties.
    ious = got10k_rect_iou(pred, gt)
    assume(np.all(np.abs(ious[:, None] - np.linspace(0, 1, 21)[None, 1:-1]) > 1e-9))
    s = metrics.score(pred, gt)
    np.testing.assert_allclose(metrics.iou(pred, gt), got10k_rect_iou(pred, gt), atol=1e-9)
    np.testing.assert_allclose(s.success, succ)
    np.testing.assert_allclose(s.precision, prec)
    assert s.auc == pytest.approx(auc) and s.precision20 == pytest.approx(p20)


def pysot_curves(gt, pred):
    """pysot's OPEBenchmark: success_overlap and success_error over all frames (an independent re-statement)."""
    n = len(gt)
    iou = -np.ones(n)
    scored = np.sum(gt[:, 2:] > 0, axis=1) == 2
    g, r = gt[scored], pred[scored]
    inter = (np.maximum(0, np.minimum(r[:, 0] + r[:, 2], g[:, 0] + g[:, 2]) - np.maximum(r[:, 0], g[:, 0]))
             * np.maximum(0, np.minimum(r[:, 1] + r[:, 3], g[:, 1] + g[:, 3]) - np.maximum(r[:, 1], g[:, 1])))
    with np.errstate(invalid="ignore", divide="ignore"):
        iou[scored] = np.maximum(np.minimum(1, inter / (r[:, 2] * r[:, 3] + g[:, 2] * g[:, 3] - inter)), 0)
    succ = np.array([np.sum(iou > t) / n for t in np.arange(0, 1.05, 0.05)])
    centre_gt, centre = gt[:, :2] + (gt[:, 2:] - 1) / 2, pred[:, :2] + (pred[:, 2:] - 1) / 2
    dist = -np.ones(n)
    present = np.sum(centre_gt > 0, axis=1) == 2
    dist[present] = np.sqrt(np.sum((centre_gt[present] - centre[present]) ** 2, axis=1))
    return succ, np.array([np.sum(dist <= t) / n for t in np.arange(0, 51)])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(box, box, st.sampled_from(["kept", "nan gt", "nan pred", "empty pred", "far pred"])),
                min_size=1, max_size=40))
def test_absent_toolkit_matches_pysot_on_absent_targets_and_broken_predictions(rows):
    """absent="toolkit" against pysot's formulas, with NaN ground truth, NaN, empty or negative predictions and
    predictions far outside the image (targets with their centre right of and below (0, 0), where pysot's test
    of an absent target agrees with an empty box: see the module docstring of metrics)."""
    gt = np.array([g for _, g, _ in rows], float)
    pred = np.array([p for p, _, _ in rows], float)
    kinds = np.array([kind for _, _, kind in rows])
    gt[kinds == "nan gt"] = np.nan
    pred[kinds == "nan pred"] = np.nan
    pred[kinds == "empty pred", 2:] = [0, -5]
    pred[kinds == "far pred", :2] -= 5000
    assume(np.all(gt[kinds != "nan gt", :2] + (gt[kinds != "nan gt", 2:] - 1) / 2 > 0))
    valid = metrics.valid_mask(gt)
    assume(valid.any())
    ious = metrics.iou(pred[valid], gt[valid])
    assume(np.all(np.abs(ious[:, None] - np.linspace(0, 1, 21)[None, 1:-1]) > 1e-9))
    succ, prec = pysot_curves(gt, pred)
    np.testing.assert_allclose(metrics.success_curve(pred, gt, absent="toolkit"), succ)
    np.testing.assert_allclose(metrics.precision_curve(pred, gt, absent="toolkit"), prec)


@settings(max_examples=30, deadline=None)
@given(arrays(np.int64, (10, 4), elements=st.integers(1, 400)), st.integers(-3, 3))
def test_invariant_to_common_shift(boxes, shift):
    """0- vs 1-based files give the same scores (exact integer-valued boxes: no rounding at thresholds)."""
    gt = boxes.astype(np.float64) / 4
    pred = boxes[::-1].copy()
    a = metrics.score(pred, gt)
    b = metrics.score(pred + [shift, shift, 0, 0], gt + [shift, shift, 0, 0])
    np.testing.assert_allclose(a.success, b.success, atol=1e-12)
    np.testing.assert_allclose(a.precision, b.precision, atol=1e-12)


# --- the lost flag ---------------------------------------------------------------------------------------------
def test_lost_flag_rates_hand_case():
    overlaps = np.array([0.0, 0.05, 0.09, 0.3, 0.6, 0.8, 0.9, 0.95])  # 3 failures, 1 in between, 4 tracked
    lost = np.array([True, True, False, True, False, True, False, False])
    rates = metrics.lost_flag_rates(lost, overlaps)
    assert (rates["frames"], rates["failures"], rates["tracked"]) == (8, 3, 4)
    assert rates["flagged"] == 4 / 8 and rates["failures_flagged"] == 2 / 3 and rates["tracked_flagged"] == 1 / 4
    assert rates["flags_on_failures"] == 2 / 4  # the flag on IoU 0.3 is neither right nor a false alarm
    never = metrics.lost_flag_rates(np.zeros(8, bool), overlaps)
    assert never["failures_flagged"] == 0 and np.isnan(never["flags_on_failures"])


def test_an_overlap_at_a_lost_flag_bound_counts_for_neither_side():
    """A failure is IoU < 0.1 and a tracked frame IoU > 0.5, as the README says: a frame at either bound is
    neither, in the rates as in the curve."""
    overlaps = np.array([metrics.FAILURE_IOU, metrics.TRACKED_IOU, 0.0, 1.0])
    rates = metrics.lost_flag_rates(np.ones(4, bool), overlaps)
    assert (rates["failures"], rates["tracked"], rates["flags_on_failures"]) == (1, 1, 1 / 4)
    # thresholds 1, 2, 3: the frames at the bounds, flagged from 2 on, move neither share
    _, failures_flagged, tracked_flagged = metrics.lost_flag_curve([1.0, 1.0, 2.0, 2.0], overlaps)
    np.testing.assert_array_equal(failures_flagged, [0, 0, 1])
    np.testing.assert_array_equal(tracked_flagged, [0, 0, 1])


def test_lost_flag_curve_hand_case():
    confidence = np.array([5.0, 30.0, np.nan, 10.0, 40.0, 50.0])
    overlaps = np.array([0.0, 0.0, 0.0, 0.7, 0.7, 0.7])  # three failures (one without a confidence), three tracked
    thresholds, failures_flagged, tracked_flagged = metrics.lost_flag_curve(confidence, overlaps)
    np.testing.assert_array_equal(thresholds, [5, 10, 30, 40, 50, 51])
    # flag = confidence < threshold; the failure without a confidence is never flagged
    np.testing.assert_allclose(failures_flagged, [0, 1 / 3, 1 / 3, 2 / 3, 2 / 3, 2 / 3])
    np.testing.assert_allclose(tracked_flagged, [0, 0, 1 / 3, 1 / 3, 2 / 3, 1])
    for threshold, caught, wrong in zip(thresholds, failures_flagged, tracked_flagged):
        rates = metrics.lost_flag_rates(confidence < threshold, overlaps)  # the curve is the rates' own
        assert (rates["failures_flagged"], rates["tracked_flagged"]) == pytest.approx((caught, wrong))
