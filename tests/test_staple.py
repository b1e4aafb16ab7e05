"""The Staple peer (tacf.staple): its colour response, following a generated target, bad input (its floors on the
real sequences are in test_sequences.py)."""
import cv2
import numpy as np
import pytest
from synthetic import assert_follows, moving_target_sequence

from tacf.eval.trackers import check_name, make_tracker
from tacf.staple import Staple, StapleConfig, window_means


def test_window_means_are_the_means_of_every_window():
    values = np.random.default_rng(3).random((9, 12)).astype(np.float32)
    means = window_means(values, (4, 5))
    assert means.shape == (6, 8)
    expected = [[values[i:i + 4, j:j + 5].mean() for j in range(8)] for i in range(6)]
    np.testing.assert_allclose(means, expected, rtol=1e-6)


def test_window_means_peak_where_the_likelihood_block_is():
    likelihood = np.zeros((30, 30), np.float32)
    likelihood[12:18, 7:13] = 1.0  # a 6x6 target-coloured block whose top-left pixel is (12, 7)
    means = window_means(likelihood, (6, 6))
    assert np.unravel_index(np.argmax(means), means.shape) == (12, 7)
    assert means.max() == pytest.approx(1.0)


@pytest.mark.parametrize("gray", [False, True])
def test_follows_a_moving_textured_target(gray):
    images, truth = moving_target_sequence(gray=gray)
    tracker = Staple()
    tracker.init(images[0], truth[0])
    results = [tracker.update(image) for image in images[1:]]
    assert_follows(results, truth)
    assert all(r.ok and np.isfinite(r.pme) for r in results)


def test_merge_factor_is_the_colour_response_s_weight():
    """merge_factor weighs the colour response, 1 - merge_factor the filter's. With every pixel in one colour bin
    the colour response is flat and says nothing: the colour alone (1) leaves the box in place, the filter alone
    (0) follows the target."""
    images, truth = moving_target_sequence(frames=12, gray=True)
    images = [image // 2 for image in images]   # all under 128: one bin of two

    def centres(merge_factor):
        tracker = Staple(StapleConfig(merge_factor=merge_factor, hist_bins=2))
        tracker.init(images[0], truth[0])
        return np.array([[x + w / 2, y + h / 2] for x, y, w, h in (tracker.update(i).box for i in images[1:])])

    start = truth[0, :2] + truth[0, 2:] / 2
    np.testing.assert_allclose(centres(1.0), np.tile(start, (len(images) - 1, 1)))
    assert np.abs(centres(0.0) - (truth[1:, :2] + truth[1:, 2:] / 2)).max() < 3


def test_the_gray_feature_is_centred_on_mid_grey():
    """Staple's gray channel is pixel / 255 - 0.5: a mid-grey patch gives it nothing, only 1 / 510 of a level,
    where a channel of pixel / 255 would add a windowed constant of half a level to every filter."""
    images, truth = moving_target_sequence(frames=1)
    tracker = Staple()
    tracker.init(images[0], truth[0])
    patch = np.full((*tracker.grid.patch_hw.astype(int), 3), 128, np.uint8)
    gray = np.fft.irfft2(tracker._features_hat(patch)[0], s=tracker.grid.filter_hw)
    np.testing.assert_allclose(gray, (128 / 255 - 0.5) * tracker.cosine_window, atol=1e-6)


def test_bad_input_is_refused():
    images, truth = moving_target_sequence(frames=2)
    tracker = Staple()
    with pytest.raises(RuntimeError, match="init"):
        tracker.update(images[0])
    with pytest.raises(ValueError, match="positive"):
        tracker.init(images[0], (10, 10, 0, 5))
    tracker.init(images[0], truth[0])
    with pytest.raises(ValueError, match="differs"):
        tracker.update(cv2.resize(images[1], (100, 80)))


@pytest.mark.parametrize("change", [{"padding": 0.0}, {"merge_factor": 1.5}, {"num_scales": 32},
                                    {"scale_step": 1.0}, {"lambda1": float("nan")}, {"hist_bins": 1000},
                                    {"cell_size": True}])
def test_bad_parameters_are_refused(change):
    with pytest.raises(ValueError, match="StapleConfig." + next(iter(change))):
        StapleConfig(**change)


@pytest.mark.parametrize("change, message", [
    ({"hist_bins": 3}, "power of two up to 64"),          # init failed, and update() after it with a TypeError
    ({"hist_bins": 256}, "power of two up to 64"),        # 16.7 M bins, as TrackerConfig refuses them
    ({"fixed_area": 16.0}, "the filter's cells"),         # one cell: init failed, update() after it AttributeError
    ({"fixed_area": 100.0}, "the filter's cells"),
    ({"scale_step": 2.0, "num_scales": 129}, "largest scale patch"),   # 2**64 times the target: init failed
    ({"scale_step": 2.0}, "largest scale patch"),                      # 65,536 times
])
def test_parameters_the_tracker_cannot_run_are_refused(change, message):
    with pytest.raises(ValueError, match="StapleConfig: .*" + message):
        StapleConfig(**change)


def test_tiny_target_leaving_the_image_and_a_target_larger_than_most_of_the_frame():
    images, truth = moving_target_sequence(frames=60, target=(9, 10), velocity=(0.0, 5.0))  # leaves at frame ~54
    tracker = Staple()
    tracker.init(images[0], truth[0])
    for image in images[1:]:
        x, y, w, h = tracker.update(image).box
        assert np.isfinite([x, y, w, h]).all() and w > 0 and h > 0
    images, _ = moving_target_sequence(frames=8, size=(100, 120), target=(80, 100), velocity=(0.3, 0.3))
    tracker.init(images[0], (5, 5, 110, 90))
    for image in images[1:]:
        assert np.isfinite(tracker.update(image).box).all()


def test_is_a_tracker_of_the_evaluation():
    assert check_name("staple") == "staple"
    tracker = make_tracker("staple")
    images, truth = moving_target_sequence(frames=5)
    tracker.init(images[0], tuple(truth[0]))
    box = tracker.update(images[1])
    assert len(box) == 4 and tracker.ok

