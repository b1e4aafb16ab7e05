"""Patch sampling (geometry.sample_patch, resize_auto): mexResize's 'auto' rule, the mipmap of
TrackerConfig.fast_resize, and large crops shrunk while they are cut."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tacf import Tracker, TrackerConfig
import tacf.geometry as geometry
from tacf.geometry import crop_replicate, resize_auto, sample_patch, subwindow

RNG = np.random.default_rng(7)
BOAT5 = Path(__file__).resolve().parents[2] / "shared" / "data" / "sequences" / "UAV123_10fps" / "boat5" / "img"


def random_patch(shape) -> np.ndarray:
    return RNG.integers(0, 256, shape).astype(np.uint8)


@pytest.mark.parametrize("target_hw, padding", [((200, 200), 1.0), ((100, 400), 1.0), ((199, 200), 2.5),
                                                ((50, 50), 2.5), ((25, 100), 2.5), ((49, 50), 3.0), ((1, 1), 3.0)])
def test_padding_falls_with_the_target_s_area(target_hw, padding):
    """ALGORITHM.md section 1: 1 from the fixed area (200^2) up, 2.5 from 50^2, 3 below."""
    assert geometry.search_padding(np.array(target_hw, dtype=np.float64), 200.0**2) == padding


def ramp(height: int, width: int) -> np.ndarray:
    """A float32 image whose value is the column coordinate: resampling it reads back where each pixel sampled."""
    return np.tile(np.arange(width, dtype=np.float32), (height, 1))


@pytest.mark.parametrize("shape", [(40, 50), (40, 50, 3)])
def test_authors_rule_is_bilinear_to_enlarge_and_area_to_shrink(shape):
    patch = random_patch(shape)
    assert np.array_equal(resize_auto(patch, (60, 70)), cv2.resize(patch, (70, 60), interpolation=cv2.INTER_LINEAR))
    assert np.array_equal(resize_auto(patch, (17, 23)), cv2.resize(patch, (23, 17), interpolation=cv2.INTER_AREA))
    # one axis growing, the other shrinking (DSST's scale patches of a tall or wide target): the width decides
    assert np.array_equal(resize_auto(patch, (60, 30)), cv2.resize(patch, (30, 60), interpolation=cv2.INTER_AREA))
    assert np.array_equal(resize_auto(patch, (20, 70)), cv2.resize(patch, (70, 20), interpolation=cv2.INTER_LINEAR))


@pytest.mark.parametrize("out_hw", [(60, 70), (45, 45), (30, 40), (21, 26)])
def test_fast_rule_is_bilinear_below_a_halving(out_hw):
    """Enlargements, and shrinks of less than two on some axis, are one bilinear resize."""
    patch = random_patch((40, 50, 3))
    expected = cv2.resize(patch, out_hw[::-1], interpolation=cv2.INTER_LINEAR)
    assert np.array_equal(resize_auto(patch, out_hw, fast=True), expected)


@pytest.mark.parametrize("halvings", [1, 2])
def test_fast_rule_halves_by_exact_two_by_two_means(halvings):
    patch = random_patch((64, 48, 3))
    block = 2**halvings
    block_means = patch.astype(np.float64).reshape(64 // block, block, 48 // block, block, 3).mean(axis=(1, 3))
    error = np.abs(resize_auto(patch, (64 // block, 48 // block), fast=True) - block_means)
    assert error.max() <= 0.5 * halvings  # one rounding to uint8 per halving


@pytest.mark.parametrize("source_hw", [(203, 157), (97, 130), (64, 64), (33, 250)])
@pytest.mark.parametrize("out_hw", [(25, 20), (9, 11)])
def test_fast_rule_neither_shifts_nor_stretches_the_content(source_hw, out_hw):
    """Halvings of odd sizes do not move the samples: on a ramp, every output pixel reads the coordinate an area
    resize centres it on, (x + 0.5) * source / output - 0.5, to 1/20 pixel; the first and last columns, which
    sample within half a level pixel of the border, where bilinear sampling clamps, to within a pixel."""
    out = resize_auto(ramp(*source_hw), out_hw, fast=True)
    centres = np.tile((np.arange(out_hw[1]) + 0.5) * source_hw[1] / out_hw[1] - 0.5, (out_hw[0], 1))
    np.testing.assert_allclose(out[:, 1:-1], centres[:, 1:-1], atol=0.05)
    np.testing.assert_allclose(out, centres, atol=1.0)


def test_fast_rule_stays_close_to_area_averaging_on_smooth_content():
    """On smooth content the mipmap and one area resize agree to a few grey levels (mean well under one)."""
    x, y = np.meshgrid(np.linspace(0, 6, 300), np.linspace(0, 4, 260))
    image = (127.5 + 100 * np.sin(x) * np.cos(y)).astype(np.uint8)
    for out_hw in [(200, 230), (120, 140), (40, 35)]:
        area = resize_auto(image, out_hw).astype(float)
        fast = resize_auto(image, out_hw, fast=True).astype(float)
        assert np.abs(area - fast).mean() < 0.5 and np.abs(area - fast).max() <= 3


@pytest.mark.parametrize("shrink", [1.1, 1.6, 2.7, 6.0])
def test_fast_rule_stays_close_to_area_averaging_on_a_real_frame(shrink):
    """boat5's first frame (a UAV123@10fps sequence; water, much fine texture), its 586x528 search area shrunk as the
    tracker shrinks it: 0.3, 1.2, 1.7 and 1.8 grey levels apart on average (measured)."""
    frames = sorted(BOAT5.glob("*.jpg"))
    if not frames:
        pytest.skip(f"{BOAT5} is absent")
    crop = cv2.imread(str(frames[0]))[100:628, 300:886]
    out_hw = (round(528 / shrink), round(586 / shrink))
    difference = np.abs(resize_auto(crop, out_hw).astype(float) - resize_auto(crop, out_hw, fast=True))
    assert difference.mean() < 2.0


def test_subwindow_and_the_tracker_use_the_configured_rule(monkeypatch):
    frame = random_patch((240, 320, 3))
    pos, model_hw, sample_hw = np.array([120.0, 160.0]), (50, 60), np.array([150.0, 170.0])  # rows 46-195, cols 76-245
    assert np.array_equal(subwindow(frame, pos, model_hw, sample_hw),
                          resize_auto(frame[46:196, 76:246], model_hw))
    assert np.array_equal(subwindow(frame, pos, model_hw, sample_hw, fast_resize=True),
                          resize_auto(frame[46:196, 76:246], model_hw, fast=True))
    seen = []

    def spy(patch, out_hw, fast=False):
        seen.append(fast)
        return resize_auto(patch, out_hw, fast)

    monkeypatch.setattr(geometry, "resize_auto", spy)
    for fast in (True, False):
        seen.clear()
        tracker = Tracker(TrackerConfig.profile(fast_resize=fast))
        tracker.init(frame, (140, 100, 40, 30))
        tracker.update(frame)
        assert seen and set(seen) == {fast}  # the samples and the DSST patches alike


def smooth_frame(height: int, width: int) -> np.ndarray:
    x, y = np.meshgrid(np.linspace(0, 40, width), np.linspace(0, 25, height))
    grey = 127.5 + 60 * np.sin(x) * np.cos(y) + 50 * np.sin(0.3 * x + 0.2 * y)
    return np.dstack([grey, 255 - grey, np.roll(grey, 7, axis=1)]).astype(np.uint8)


@pytest.mark.parametrize("fast", [False, True])
def test_a_large_crop_is_shrunk_while_cut_and_stays_close_to_one_cut_whole(monkeypatch, fast):
    """Over LARGE_CROP_PIXELS a crop's part in the image is averaged over blocks and its borders replicated at that
    scale, inside the image, across its borders and wholly outside; below it, the crop is cut as before."""
    image = smooth_frame(720, 1280)
    out_hw = (50, 60)
    # inside, across the first borders, across the last ones, wholly outside, across all four; measured 0.2-0.35
    # grey levels apart on average, 1.6 for the last
    cases = [((100, 200), (400, 600)), ((-150, -100), (500, 700)), ((500, 1000), (400, 500)),
             ((-900, -900), (300, 300)), ((-100, -100), (1000, 1500))]
    for top_left, size in cases:
        assert np.array_equal(sample_patch(image, top_left, size, out_hw, fast),
                              resize_auto(crop_replicate(image, top_left, size), out_hw, fast))
    monkeypatch.setattr(geometry, "LARGE_CROP_PIXELS", 1 << 14)
    for top_left, size in cases:
        whole = resize_auto(crop_replicate(image, top_left, size), out_hw, fast).astype(float)
        shrunk = sample_patch(image, top_left, size, out_hw, fast)
        assert shrunk.shape == whole.shape and np.abs(shrunk - whole).mean() < 2.0, (top_left, size)


def test_a_large_crop_with_no_whole_block_in_the_image_repeats_the_border_pixels_averaged(monkeypatch):
    """A crop overlapping the image by under a block (or not at all) on an axis took every f-th pixel of the image:
    a row f-1 inside instead of the border row, and one column in f instead of their mean (0 for 225 here)."""
    image = np.zeros((360, 640), np.uint8)
    image[-1], image[:, -1] = 200, 200          # a bright border row and column, unlike the pixels inside them
    image[:, 1::2] += 25                        # columns alternating 0 / 25
    monkeypatch.setattr(geometry, "LARGE_CROP_PIXELS", 1 << 14)
    cases = [((359, 0), (800, 640)), ((400, 0), (800, 640)), ((-800, 0), (800, 640)),   # last row, below, above
             ((0, 639), (360, 900)), ((359, 639), (900, 900))]                          # last column, corner
    for top_left, size in cases:
        whole = resize_auto(crop_replicate(image, top_left, size), (50, 60)).astype(float)
        shrunk = sample_patch(image, top_left, size, (50, 60))
        assert np.abs(shrunk - whole).mean() < 2.0, (top_left, size, np.abs(shrunk - whole).mean())


def test_a_frame_sized_box_on_a_4k_frame_takes_megabytes_not_hundreds():
    """Its search area, context sample and 33 scale patches were each cut whole at full resolution: 640 MB more
    (peak RSS) and 0.45 s a frame on 3840x2160; 1.5 GB and 0.63 s on 6000x4000. Now 90 and 83 MB, 0.11 and 0.34 s
    (measured; the frame itself is 25 MB and 72 MB)."""
    import tracemalloc

    frame = smooth_frame(2160, 3840)
    tracker = Tracker()
    tracemalloc.start()
    try:
        tracker.init(frame, (0, 0, 3840, 2160))
        tracker.update(frame)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 150e6, f"{peak / 1e6:.0f} MB"
