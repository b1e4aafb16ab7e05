"""DSST scale filter (tacf/scale.py, ALGORITHM.md section 11)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.fft

from tacf.config import TrackerConfig
from tacf.features import fhog
from tacf.geometry import NormalisedGrid, TargetAreas, search_padding
from tacf.scale import (ScaleFilter, filter_terms, scale_factors, scale_label, scale_limits, scale_model_size,
                        scale_patch_rects, scale_response, scale_window)
from tacf.tracker import Tracker

from synthetic import texture

CFG = TrackerConfig()
STEP = CFG.scale_step


def standin_features(patch: np.ndarray, cell_size: int) -> np.ndarray:
    """A cheap scale-sensitive stand-in for fHOG: cell means of intensity and of absolute x/y gradients."""
    gray = patch.max(axis=2) if patch.ndim == 3 else patch
    gy, gx = np.gradient(gray)
    cells = (gray.shape[0] // cell_size, gray.shape[1] // cell_size)
    maps = [cv2.resize(m[: cells[0] * cell_size, : cells[1] * cell_size], cells[::-1], interpolation=cv2.INTER_AREA)
            for m in (gray, np.abs(gx), np.abs(gy))]
    return np.stack(maps).astype(np.float32)


def sequence_geometry(target_sz, image_hw):
    """bg_area and norm_target_sz as the tracker's initialisation computes them (section 2)."""
    target_sz = np.asarray(target_sz, dtype=np.float64)
    areas = TargetAreas.around(target_sz, search_padding(target_sz, CFG.fixed_area), image_hw, CFG.fixed_area,
                               CFG.inner_padding)
    grid = NormalisedGrid.from_areas(areas, CFG.cell_size)
    return areas.bg_area, grid.target_hw


def make_filter(target_sz, image_hw, features=standin_features, cfg=CFG):
    bg_area, norm_target_sz = sequence_geometry(target_sz, image_hw)
    return ScaleFilter(cfg, image_hw, np.asarray(target_sz, float), norm_target_sz, bg_area, features=features)


def textured_image(hw, seed=0, channels=3):
    """Smoothed noise stretched to 0-255: texture at several scales."""
    rng = np.random.default_rng(seed)
    shape = hw if channels == 1 else (*hw, channels)
    noise = rng.standard_normal(shape).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 2.5) + 0.5 * cv2.GaussianBlur(noise, (0, 0), 6.0)
    blurred -= blurred.min()
    return (255 * blurred / blurred.max()).astype(np.uint8)


def zoom_about(image, centre_rc, zoom):
    """The image magnified by `zoom` about centre_rc (row, col): a target there appears `zoom` times larger."""
    cy, cx = centre_rc
    warp = np.array([[zoom, 0, (1 - zoom) * cx], [0, zoom, (1 - zoom) * cy]], dtype=np.float64)
    return cv2.warpAffine(image, warp, (image.shape[1], image.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)


# --- set-up values -------------------------------------------------------------------------------------------


def test_factors_run_from_largest_to_smallest_with_one_at_the_centre():
    factors = scale_factors(33, 1.03)
    assert factors.shape == (33,)
    assert factors[0] == pytest.approx(1.03**16)
    assert factors[16] == 1.0
    assert factors[32] == pytest.approx(1.03**-16)
    assert np.allclose(factors[:-1] / factors[1:], 1.03)


def test_label_is_a_centred_gaussian_with_sigma_sqrt33_over_2():
    label = scale_label(33, 0.5)
    sigma = np.sqrt(33) * 0.5  # 2.8723
    assert label[16] == 1.0
    assert label[17] == pytest.approx(np.exp(-0.5 / sigma**2))  # 0.9412
    assert label[0] == pytest.approx(np.exp(-0.5 * 16**2 / 33 / 0.25))  # exp(-128/8.25)
    assert label[0] == pytest.approx(1.8e-7, rel=0.05)
    assert np.allclose(label, label[::-1])


def test_window_is_the_symmetric_hann_with_zero_ends():
    window = scale_window(33)
    assert window[0] == 0.0 and window[32] == pytest.approx(0.0, abs=1e-15)
    assert window[16] == 1.0
    assert window[8] == pytest.approx(0.5)  # 0.5 * (1 - cos(2 pi 8 / 32))
    assert window[1] == pytest.approx(0.5 * (1 - np.cos(2 * np.pi / 32)))


def test_limits_of_the_worked_example_of_section_2():
    min_scale, max_scale = scale_limits(1.03, (720, 1280), np.array([38.0, 11.0]), np.array([112.0, 85.0]))
    assert min_scale == pytest.approx(1.03**-95)
    assert min_scale == pytest.approx(0.0603, abs=1e-4)
    assert max_scale == pytest.approx(1.03**99)
    assert max_scale == pytest.approx(18.66, abs=0.01)


@pytest.mark.parametrize("image_hw, box", [((5, 200), (50, 0, 20, 4)), ((6, 300), (50, 1, 30, 4)),
                                            ((100, 100), (50, 50, 1, 1))], ids=["5px-frame", "6px-frame", "1x1-box"])
def test_the_first_box_s_scale_is_within_the_limits(image_hw, box):
    """Where the background area is under 5 px, the code's minimum scale is above 1 (and may pass the maximum):
    identical frames grew the box 1.23 to 1.7 times on the first update. (On a frame a few pixels high the scale
    samples are mostly replicated border, and a step or two either way is noise.)"""
    image = texture(np.random.default_rng(0), (*image_hw, 3), blur=1.5)
    tracker = Tracker()
    tracker.init(image, box)
    assert tracker.scale_filter._min_scale <= 1.0 <= tracker.scale_filter._max_scale
    assert 1 / STEP**3 < tracker.update(image).scale < STEP**3


def test_model_size_of_the_worked_example_and_the_area_cap():
    assert np.array_equal(scale_model_size([129, 73], 512, 4), [30, 17])
    assert np.array_equal(scale_model_size([20, 16], 512, 4), [20, 16])  # area 320 <= 512: unchanged
    assert np.array_equal(scale_model_size([400, 4], 512, 4), [226, 4])  # degenerate: at least one cell


def test_geometry_helper_reproduces_the_worked_example():
    bg_area, norm_target_sz = sequence_geometry([38, 11], (720, 1280))
    assert np.array_equal(bg_area, [112, 85]) and np.array_equal(norm_target_sz, [129, 73])
    sf = make_filter([38, 11], (720, 1280))
    assert np.array_equal(sf.model_size, [30, 17])
    assert sf.min_scale == pytest.approx(0.0603, abs=1e-4) and sf.max_scale == pytest.approx(18.66, abs=0.01)


def test_patch_rectangles_use_floor_sizes_and_positions():
    factors = scale_factors(33, 1.03)
    top_left, sizes = scale_patch_rects(np.array([100.7, 50.2]), np.array([38.0, 11.0]), 1.0, factors)
    assert np.array_equal(sizes[16], [38, 11])
    assert np.array_equal(sizes[0], np.floor(np.array([38.0, 11.0]) * 1.03**16))  # [61, 17]
    # MATLAB 1-based first row: floor(101.7) + 1 - 19 = 83 -> 0-based 82 = floor(100.7) + 1 - 19.
    assert np.array_equal(top_left[16], [82, 46])
    _, tiny = scale_patch_rects(np.zeros(2), np.array([3.0, 3.0]), 0.1, factors)
    assert tiny.min() == 2


# --- the filter ----------------------------------------------------------------------------------------------


def test_estimate_before_training_is_an_error():
    sf = make_filter([40, 50], (240, 320))
    with pytest.raises(RuntimeError):
        sf.estimate(textured_image((240, 320)), np.array([120.0, 160.0]), 1.0)


def test_training_on_a_still_frame_keeps_the_scale():
    image = textured_image((240, 320))
    pos = np.array([120.0, 160.0])
    sf = make_filter([40, 50], image.shape[:2])
    sf.update_model(image, pos, 1.0)
    assert sf.estimate(image, pos, 1.0) == 1.0
    assert 1.0 <= sf.estimate(image, pos, 1.2) < 1.2  # the estimate moves towards the trained scale


def test_first_update_sets_and_later_updates_blend_with_the_learning_rate():
    image_a, image_b = textured_image((240, 320), seed=1), textured_image((240, 320), seed=2)
    pos = np.array([120.0, 160.0])
    single_a, single_b, blended = (make_filter([40, 50], image_a.shape[:2]) for _ in range(3))
    single_a.update_model(image_a, pos, 1.0)
    single_b.update_model(image_b, pos, 1.0)
    blended.update_model(image_a, pos, 1.0)
    blended.update_model(image_b, pos, 1.0)
    rate = CFG.scale_learning_rate
    assert np.allclose(blended._num, (1 - rate) * single_a._num + rate * single_b._num)
    assert np.allclose(blended._den, (1 - rate) * single_a._den + rate * single_b._den)


def test_filter_algebra_matches_the_full_complex_fft_formulation():
    """num = Ys conj(Xs), den = sum |Xs|^2, r = real(ifft(sum(num Xs) / (den + lambda))) over 33 scales."""
    image, probe = textured_image((240, 320), seed=3), textured_image((240, 320), seed=4)
    pos = np.array([118.3, 161.9])
    sf = make_filter([40, 50], image.shape[:2])
    sf.update_model(image, pos, 1.0)
    train, test = np.fft.fft(sf.sample(image, pos, 1.0), axis=0), np.fft.fft(sf.sample(probe, pos, 1.0), axis=0)
    label_hat = np.fft.fft(scale_label(33, 0.5))
    num = label_hat[:, None] * np.conj(train)
    den = np.sum(train * np.conj(train), axis=1)
    expected = np.real(np.fft.ifft(np.sum(num * test, axis=1) / (den + CFG.scale_lambda)))
    best = int(np.argmax(expected))
    assert sf.estimate(probe, pos, 1.0) == pytest.approx(np.clip(scale_factors(33, 1.03)[best], sf.min_scale,
                                                                 sf.max_scale))


@pytest.mark.parametrize("shift", [-5, -1, 0, 3, 7])
def test_a_sample_shifted_along_the_scale_axis_moves_the_peak_the_other_way(shift):
    """z_i = x_(i+shift): the object looks 1.03^shift larger, the response peaks at centre - shift."""
    rng = np.random.default_rng(shift + 10)
    train = rng.standard_normal((33, 50))
    probe = np.roll(train, -shift, axis=0)
    label_hat = scipy.fft.rfft(scale_label(33, 0.5))
    num, den = filter_terms(label_hat, scipy.fft.rfft(train, axis=0))
    response = scale_response(num, den, scipy.fft.rfft(probe, axis=0), 1e-4, 33)
    assert response.shape == (33,)
    assert int(np.argmax(response)) == 16 - shift
    assert scale_factors(33, 1.03)[16 - shift] == pytest.approx(1.03**shift)
    assert np.allclose(response, np.roll(scale_label(33, 0.5), -shift), atol=1e-3)


def test_sample_rows_are_windowed_and_the_zero_weight_scales_are_zero():
    image = textured_image((240, 320))
    sf = make_filter([40, 50], image.shape[:2])
    sample = sf.sample(image, np.array([120.0, 160.0]), 1.0)
    cells = sf.model_size // CFG.cell_size
    assert sample.shape == (33, 3 * cells[0] * cells[1])
    assert not sample[0].any() and not sample[32].any()
    assert sample[16].any()


def test_a_sample_without_gradients_keeps_the_scale():
    """On a blank frame fHOG gives nothing: the response is 0 at every scale, and its first maximum, the largest
    scale, grew the box on each such frame. tacf.tracker skips a blank frame before this filter; Staple does not."""
    image = textured_image((240, 320))
    pos = np.array([120.0, 160.0])
    sf = make_filter([40, 50], image.shape[:2], features=None)
    sf.update_model(image, pos, 1.0)
    blank = np.full_like(image, 128)
    assert sf.estimate(blank, pos, 1.0) == 1.0 and sf.estimate(blank, pos, 1.1) == 1.1


def test_scale_is_clamped_at_both_limits():
    image = textured_image((200, 200))
    pos = np.array([100.0, 100.0])
    sf = make_filter([40, 40], image.shape[:2])
    sf.update_model(image, pos, 1.0)
    too_big = sf.max_scale * STEP**17  # even the smallest relative scale 1.03^-16 stays above max_scale
    too_small = sf.min_scale / STEP**17
    assert sf.estimate(image, pos, too_big) == sf.max_scale
    assert sf.estimate(image, pos, too_small) == sf.min_scale


def test_grayscale_frames_work():
    gray = textured_image((360, 480), seed=5, channels=1)
    pos = np.array([180.0, 240.0])
    sf = make_filter([60, 80], gray.shape, features=fhog)
    sf.update_model(gray, pos, 1.0)
    assert sf.estimate(gray, pos, 1.0) == 1.0
    assert within_one_step(sf.estimate(zoom_about(gray, pos, STEP**2), pos, 1.0), STEP**2)


@pytest.mark.parametrize("pos", [(5.0, 5.0), (-30.0, 150.0), (235.0, 330.0)])
def test_target_partly_or_wholly_outside_the_image_does_not_crash(pos):
    image = textured_image((240, 320))
    # scale_min_visible 0, as the code: the patches are sampled however little of the box is in the frame
    sf = make_filter([40, 50], image.shape[:2], features=fhog, cfg=CFG.replace(scale_min_visible=0.0))
    sf.update_model(image, np.array(pos), 1.0)
    new_factor = sf.estimate(image, np.array(pos) + 3, 1.1)
    assert np.isfinite(new_factor) and sf.min_scale <= new_factor <= sf.max_scale


def test_a_box_mostly_beyond_the_frame_neither_moves_nor_teaches_the_scale():
    """Under scale_min_visible (half) of the box in the frame, the scale patches are mostly repeated border pixels:
    the filter keeps the scale factor and its model; from half the box in the frame on it estimates and learns."""
    image = textured_image((240, 320))
    sf = make_filter([40, 50], image.shape[:2], features=fhog)
    sf.update_model(image, np.array([200.0, 280.0]), 1.0)
    model = sf._num.copy(), sf._den.copy()
    beyond_corner = np.array([250.0, 330.0])  # 10 x 15 pixels of the 40 x 50 box in the frame
    assert not sf.sees_enough(image, beyond_corner, 1.0)
    assert sf.estimate(image, beyond_corner, 1.1) == 1.1
    sf.update_model(image, beyond_corner, 1.0)
    assert np.array_equal(sf._num, model[0]) and np.array_equal(sf._den, model[1])
    half_in = np.array([240.0, 160.0])  # the box's upper half
    assert sf.sees_enough(image, half_in, 1.0)
    sf.update_model(image, half_in, 1.0)
    assert not np.array_equal(sf._num, model[0])


@pytest.mark.parametrize("channels", [3, 1])
def test_default_batched_fhog_equals_fhog_patch_by_patch(channels):
    """The default filter computes all scale patches in one fhog_batch call; the values are those of one fhog
    call per patch, also for patches crossing the image border and for a thin, one-cell-high model."""
    image = textured_image((240, 320), seed=7, channels=channels)
    cases = [([38, 11], None, (118.4, 161.6), 1.0), ([40, 50], None, (3.0, 300.0), 1.3),
             ([9, 60], [6, 80], (200.0, 100.0), 0.9)]  # the last one forces a 6x80 model: 1x20 cells
    for target_sz, norm_target_sz, pos, scale_factor in cases:
        bg_area, default_norm_sz = sequence_geometry(target_sz, image.shape[:2])
        norm_target_sz = default_norm_sz if norm_target_sz is None else norm_target_sz
        batched, by_patch = (ScaleFilter(CFG, image.shape[:2], np.asarray(target_sz, float), norm_target_sz,
                                         bg_area, features=features) for features in (None, fhog))
        np.testing.assert_array_equal(batched.sample(image, np.array(pos), scale_factor),
                                      by_patch.sample(image, np.array(pos), scale_factor))
    assert np.array_equal(batched.model_size, [6, 80])


def within_one_step(estimated, expected):
    return abs(np.log(estimated / expected) / np.log(STEP)) <= 1 + 1e-9


@pytest.mark.parametrize("k", [-3, 0, 2, 4])
def test_synthetic_zoom_is_recovered_within_one_step(k):
    image = textured_image((360, 480), seed=5)
    pos = np.array([180.0, 240.0])
    sf = make_filter([60, 80], image.shape[:2], features=fhog)
    sf.update_model(image, pos, 1.0)
    assert within_one_step(sf.estimate(zoom_about(image, pos, STEP**k), pos, 1.0), STEP**k)


@pytest.mark.parametrize("k", [-6, 5])
def test_repeated_estimates_converge_on_a_larger_zoom(k):
    """One estimate under-shoots a big zoom (the features change smoothly with scale); repeating it, as the
    tracker does frame after frame, walks on to the true scale."""
    image = textured_image((360, 480), seed=6)
    pos = np.array([180.0, 240.0])
    sf = make_filter([38, 11], image.shape[:2], features=fhog)
    sf.update_model(image, pos, 1.0)
    zoomed = zoom_about(image, pos, STEP**k)
    scale_factor = 1.0
    for _ in range(5):
        scale_factor = sf.estimate(zoomed, pos, scale_factor)
    assert within_one_step(scale_factor, STEP**k)
