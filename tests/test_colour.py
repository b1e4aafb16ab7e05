"""The colour-histogram likelihood window (tacf/colour.py)."""
import numpy as np
import pytest

from tacf.colour import ColourModel, _per_pixel


def _bin_index(patch, bins):
    """The joint histogram bin of each pixel, the first channel varying slowest; the quantised value for gray."""
    q = patch.astype(np.int64) // (256 // bins)
    return q if q.ndim == 2 else (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


@pytest.mark.parametrize("bins", [8, 32, 64])
def test_per_pixel_lookup_reads_each_pixel_s_joint_bin(bins):
    patch = np.random.default_rng(0).integers(0, 256, (9, 7, 3), dtype=np.uint8)
    bits = bins.bit_length() - 1
    values = np.random.default_rng(1).random(bins**3).astype(np.float32)
    np.testing.assert_array_equal(_per_pixel(values, patch, 8 - bits, bits), values[_bin_index(patch, bins)])
    gray = np.ascontiguousarray(patch[..., :1])
    np.testing.assert_array_equal(_per_pixel(values[:bins], gray, 8 - bits, bits),
                                  values[_bin_index(gray[..., 0], bins)])


@pytest.mark.parametrize("channels", [3, 1])
def test_histograms_count_the_bin_index_under_each_mask(channels):
    """OpenCV's counts (ColourModel._histograms) are those of the bin index under the masks, normalised."""
    patch = np.random.default_rng(1).integers(0, 256, (40, 36, 3), dtype=np.uint8)
    patch = patch if channels == 3 else patch[..., 0].copy()
    model = ColourModel(patch, np.array([40.0, 36.0]), np.array([12.0, 10.0]), np.array([16.0, 14.0]),
                        bins=32, learning_rate=0.02, floor=0.1)
    index = _bin_index(patch, 32)
    for hist, mask in ((model.fg_hist, model.fg_mask), (model.bg_hist, model.bg_mask)):
        assert 0 < mask.sum() < mask.size
        counts = np.bincount(index[mask.astype(bool)], minlength=32**channels)
        np.testing.assert_array_equal(hist, counts / counts.sum())


def test_masks_are_the_centred_blocks_of_their_own_height_and_width():
    """The foreground mask is the fg_area block at the patch's centre, the background mask all but the target's
    block: with margins that differ by axis (a box as wide as the frame, its area cut to the frame), each its own."""
    patch = np.zeros((40, 80, 3), np.uint8)
    model = ColourModel(patch, np.array([40.0, 80.0]), fg_area=np.array([10.0, 60.0]), target_hw=np.array([20.0, 70.0]),
                        bins=32, learning_rate=0.02, floor=0.1)
    fg, bg = np.zeros((40, 80), np.uint8), np.ones((40, 80), np.uint8)
    fg[15:25, 10:70] = 1
    bg[10:30, 5:75] = 0
    np.testing.assert_array_equal(model.fg_mask, fg)
    np.testing.assert_array_equal(model.bg_mask, bg)


def _target_on_background(size=96, target=32, target_bgr=(20, 20, 220), background_bgr=(30, 160, 40)):
    patch = np.empty((size, size, 3), np.uint8)
    patch[:] = background_bgr
    start = (size - target) // 2
    patch[start:start + target, start:start + target] = target_bgr
    return patch


def test_likelihood_is_high_on_the_target_colour_and_floored_on_the_background():
    patch = _target_on_background()
    area = np.array([96.0, 96.0])
    model = ColourModel(patch, area, fg_area=np.array([26.0, 26.0]), target_hw=np.array([32.0, 32.0]),
                        bins=32, learning_rate=0.02, floor=0.1)
    window = model.likelihood_window(patch, (24, 24))
    assert window.shape == (24, 24) and window.dtype == np.float32
    assert window[10:14, 10:14].min() == pytest.approx(1.0)  # target colour: only ever seen in the foreground
    assert window[:3, :3].max() == pytest.approx(0.1)  # background colour: floored
    # The target moves: the window follows its colour, not the patch centre.
    moved = np.roll(patch, (20, 20), axis=(0, 1))
    moved_window = model.likelihood_window(moved, (24, 24))
    assert moved_window[15:19, 15:19].min() == pytest.approx(1.0) and moved_window[5, 5] == pytest.approx(0.1)


def test_uniform_patch_gives_a_neutral_window():
    patch = np.full((64, 64, 3), 128, np.uint8)
    model = ColourModel(patch, np.array([64.0, 64.0]), np.array([16.0, 16.0]), np.array([20.0, 20.0]),
                        bins=32, learning_rate=0.02, floor=0.1)
    np.testing.assert_array_equal(model.likelihood_window(patch, (16, 16)), np.ones((16, 16), np.float32))


def test_update_blends_the_histograms():
    patch = _target_on_background()
    model = ColourModel(patch, np.array([96.0, 96.0]), np.array([26.0, 26.0]), np.array([32.0, 32.0]),
                        bins=32, learning_rate=0.5, floor=0.1)
    recoloured = _target_on_background(target_bgr=(220, 20, 20))
    model.update(recoloured)
    new_bin = _bin_index(np.array([[[220, 20, 20]]], np.uint8), 32)
    old_bin = _bin_index(np.array([[[20, 20, 220]]], np.uint8), 32)
    assert model.fg_hist[new_bin[0, 0]] == pytest.approx(model.fg_hist[old_bin[0, 0]])  # half and half
    assert model.fg_hist.sum() == pytest.approx(1.0) and model.bg_hist.sum() == pytest.approx(1.0)
