"""Accuracy on the real UAV sequences of ../shared/data/sequences: mean IoU floors that the trackers reach.

The floors sit a little under what the default profile (and the Staple peer) measured (README "Accuracy"), so
that a regression in any module shows up as a failing sequence. Skipped when the data is absent.
"""
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacf import Tracker, TrackerConfig
from tacf.eval.metrics import iou
from tacf.staple import Staple

SEQUENCES = Path(__file__).resolve().parents[2] / "shared" / "data" / "sequences"

# sequence: mean IoU floor for the default profile (measured values in the README)
DEFAULT_PROFILE_FLOORS = {
    "UAV123_10fps/boat5": 0.45,
    "UAV123_10fps/building5": 0.70,
    "UAV123_10fps/car16_1": 0.40,
    "UAV123_10fps/person12_1": 0.65,
    "UAV123_10fps/truck2": 0.60,  # lost by frame 10 without the motion search (mean IoU 0.06)
    "UAV123_10fps/wakeboard10": 0.35,  # 0.39 one pass; 0.35-0.57 from first boxes 1 px away (README "Accuracy")
    "UAV123_10fps/wakeboard7": 0.45,
    "DTB70/MountainBike6": 0.45,
    "DTB70/Surfing06": 0.28,
    "UAVDT/S0601": 0.22,
}


def _load(name: str):
    folder = SEQUENCES / name
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    frames = [cv2.imread(str(p)) for p in sorted((folder / "img").glob("*.jpg"))]
    truth = np.loadtxt(folder / "groundtruth.txt", delimiter=",")
    truth[:, :2] -= 1  # the benchmark files are 1-based
    return frames, truth


def _mean_iou(boxes: np.ndarray, truth: np.ndarray) -> float:
    valid = ~np.isnan(truth).any(axis=1)
    return float(np.mean(iou(boxes[valid], truth[valid])))


def _track(tracker, frames, first_box) -> np.ndarray:
    tracker.init(frames[0], first_box)
    return np.array([first_box] + [tracker.update(frame).box for frame in frames[1:]])


@pytest.mark.data
@pytest.mark.parametrize("name", sorted(DEFAULT_PROFILE_FLOORS))
def test_default_profile_reaches_its_floor(name):
    frames, truth = _load(name)
    boxes = _track(Tracker(TrackerConfig.profile()), frames, truth[0])
    assert _mean_iou(boxes, truth) > DEFAULT_PROFILE_FLOORS[name]


# The Staple peer (tacf.staple), whose floors sit a little under what it measured (mean IoU 0.84, 0.76, 0.78)
STAPLE_FLOORS = {"UAV123_10fps/building5": 0.75, "UAV123_10fps/person12_1": 0.65, "OTB100/Crossing": 0.70}


@pytest.mark.data
@pytest.mark.parametrize("name", sorted(STAPLE_FLOORS))
def test_staple_reaches_its_floor(name):
    frames, truth = _load(name)
    assert _mean_iou(_track(Staple(), frames, truth[0]), truth) > STAPLE_FLOORS[name]


@pytest.mark.data
def test_a_partial_dropout_over_the_target_is_sat_out():
    """building5 with a grey block, six times the target's size, over the target for ten frames from a third of the
    way in (a lost part of corrupt frames). Searched and learnt, the box slid 190 px to the block's edge and never
    came back (mean IoU after it 0.00); kept in place, it finds the building again (0.85, as without the block)."""
    frames, truth = _load("UAV123_10fps/building5")
    start = len(frames) // 3
    x, y, w, h = truth[start].astype(int)
    rows = slice(max(y + h // 2 - 3 * h, 0), y + h // 2 + 3 * h)
    columns = slice(max(x + w // 2 - 3 * w, 0), x + w // 2 + 3 * w)
    for frame in frames[start:start + 10]:
        frame[rows, columns] = 128
    boxes = _track(Tracker(TrackerConfig.profile()), frames, truth[0])
    assert _mean_iou(boxes[start + 10:], truth[start + 10:]) > 0.75
