"""The Tracker API: following a generated moving target, every profile and switch, and bad input."""
import dataclasses
import json
from fractions import Fraction

import cv2
import numpy as np
import pytest

from tacf import Tracker, TrackerConfig, TrackResult
from tacf.boxes import visible_fraction
from tacf.config import PROFILES
from tacf.eval.metrics import box_iou
from tacf.staple import Staple
from synthetic import assert_follows, leaving_sequence, moving_target_sequence, texture


def _track(config, images, first_box):
    tracker = Tracker(config)
    tracker.init(images[0], first_box)
    return [tracker.update(image) for image in images[1:]]


CONFIGS = {
    "authors": TrackerConfig.profile("authors"),
    "paper": TrackerConfig.profile("paper"),
    "kcc": TrackerConfig.profile("kcc"),
    "kcc+sa": TrackerConfig.profile("kcc", spatiotemporal_attention=True),
    "kcc+da": TrackerConfig.profile("kcc", dimensional_attention=True),
    "kcc+ca": TrackerConfig.profile("kcc", context_attention=True),
    "no-scale-no-colour-hog-only": TrackerConfig.profile("authors", scale_estimation=False, colour_window=False,
                                                         use_colour_names=False),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_follows_a_moving_textured_target(name):
    images, truth = moving_target_sequence()
    results = _track(CONFIGS[name], images, truth[0])
    assert_follows(results, truth)
    assert all(isinstance(r, TrackResult) and r.ok for r in results[:5])


def _mean_iou(config, images, truth) -> float:
    return float(np.mean([box_iou(r.box, t) for r, t in zip(_track(config, images, truth[0]), truth[1:])]))


def test_motion_search_follows_a_target_faster_than_the_search_radius():
    # Speeding up to 30 px a frame: the search area reaches about 30 px from the last position, so a search
    # there alone loses the target; the second search, where the last move continues, keeps it.
    steps = [(0.0, min(5.0 * k, 30.0)) for k in range(1, 40)]
    images, truth = moving_target_sequence(size=(240, 1400), steps=steps)
    assert _mean_iou(TrackerConfig.profile("paper", motion_search=False), images, truth) < 0.4
    for profile in ("paper", "authors", "kcc"):
        assert _mean_iou(TrackerConfig.profile(profile), images, truth) > 0.85, profile


@pytest.mark.parametrize("then", [(0.0, 0.0), (0.0, -25.0)], ids=["stops", "turns-back"])
def test_motion_search_lets_a_fast_target_stop_or_turn_back(then):
    # The search where the move continues finds background there, and the search at the last position wins.
    steps = [(0.0, 5.0 * k) for k in range(1, 6)] + [(0.0, 25.0)] * 4 + [then] * 10
    images, truth = moving_target_sequence(size=(240, 640), steps=steps)
    assert _mean_iou(TrackerConfig.profile("paper"), images, truth) > 0.85


def test_grayscale_frames():
    images, truth = moving_target_sequence(frames=25, gray=True)
    assert _mean_iou(TrackerConfig.profile(), images, truth) > 0.6


def test_one_channel_frames_are_tracked_as_gray_ones():
    """An H x W x 1 frame (a gray image read with its channel axis kept) is the H x W one: the same boxes."""
    images, truth = moving_target_sequence(frames=6, gray=True)
    gray, one_channel = Tracker(), Tracker()
    gray.init(images[0], truth[0])
    one_channel.init(images[0][:, :, None], truth[0])
    for image in images[1:]:
        assert one_channel.update(image[:, :, None]).box == gray.update(image).box


def test_scale_estimate_follows_a_growing_target():
    rng = np.random.default_rng(3)
    background = texture(rng, (300, 300, 3), blur=4)
    sprite = cv2.add(texture(rng, (40, 40, 3), blur=2), 50)
    images, sizes = [], []
    for k in range(30):
        side = int(round(40 * 1.01**k))
        image = background.copy()
        top = 150 - side // 2
        image[top:top + side, top:top + side] = cv2.resize(sprite, (side, side))
        images.append(image)
        sizes.append(side)
    tracker = Tracker(TrackerConfig.profile())
    tracker.init(images[0], (130, 130, 40, 40))
    for image in images[1:]:
        result = tracker.update(image)
    assert result.scale > 1.15  # the truth is 1.01^29 = 1.33; the scale filter moves by 3 % steps
    assert abs(result.box[2] - sizes[-1]) < 0.2 * sizes[-1]


def test_reinit_restarts_on_a_new_box():
    images, truth = moving_target_sequence(frames=20)
    tracker = Tracker()
    tracker.init(images[0], truth[0])
    for image in images[1:10]:
        tracker.update(image)
    tracker.init(images[10], truth[10])
    assert tracker.box == pytest.approx(tuple(truth[10]), abs=1.0)
    result = tracker.update(images[11])
    assert box_iou(result.box, truth[11]) > 0.6


def test_tiny_target_and_target_leaving_the_image():
    images, truth = moving_target_sequence(frames=60, target=(9, 10), velocity=(0.0, 5.0))
    tracker = Tracker()
    tracker.init(images[0], truth[0])
    for image in images[1:]:  # the target leaves through the right edge around frame 54
        result = tracker.update(image)
        assert all(np.isfinite(result.box)) and result.box[2] > 0 and result.box[3] > 0
    x, y, w, h = result.box
    assert -w < x < images[0].shape[1] and -h < y < images[0].shape[0]


def test_target_larger_than_most_of_the_frame():
    images, truth = moving_target_sequence(frames=8, size=(100, 120), target=(80, 100), velocity=(0.3, 0.3))
    tracker = Tracker()
    tracker.init(images[0], (5, 5, 110, 90))
    for image in images[1:]:
        assert np.all(np.isfinite(tracker.update(image).box))


@pytest.mark.parametrize("frame, message", [
    (None, "numpy array"),
    (np.zeros((0, 0, 3), np.uint8), "empty"),
    (np.zeros((50, 50, 4), np.uint8), "HxWx3"),
    (np.zeros((50, 50, 3), np.float32), "uint8"),
    (np.zeros((2, 64, 3), np.uint8), "under 3 pixels a side"),   # its background area rounded to 0 pixels
])
def test_bad_frames_raise_clear_errors(frame, message):
    with pytest.raises(ValueError, match=message):
        Tracker().init(frame, (1, 1, 10, 10))


def test_frames_of_any_memory_layout_are_tracked_as_their_copies():
    """A sliding_window_view's rows overlap in memory, which OpenCV's Mat refuses: init raised cv2.error
    ("_step >= minstep") from inside the resize. Views, broadcast and Fortran-ordered frames give the boxes of their
    contiguous copies."""
    rng = np.random.default_rng(8)
    colour = texture(rng, (120, 320, 3), blur=2)
    row = texture(rng, (1, 400), blur=2)[0]
    frames = [np.lib.stride_tricks.sliding_window_view(row, 160)[:120],  # each row the last one moved by a pixel
              np.broadcast_to(row[:160], (120, 160)), np.asfortranarray(colour), colour[::-1, ::2, ::-1]]
    for frame in frames:
        boxes = []
        for copy in (frame, np.ascontiguousarray(frame)):
            tracker = Tracker()
            tracker.init(copy, (50, 40, 20, 16))
            boxes.append([tracker.update(copy).box for _ in range(2)])
        assert boxes[0] == boxes[1]


def test_a_config_that_is_no_tracker_config_is_a_clear_error():
    """Tracker("kcc") failed only in init, with "'str' object has no attribute 'fixed_area'"."""
    for config in ("kcc", {"cell_size": 4}, TrackerConfig.profile):
        with pytest.raises(TypeError, match="TrackerConfig.profile"):
            Tracker(config)


@pytest.mark.parametrize("box, message", [
    ((10, 10, 0, 5), "positive"),
    ((10, 10, -3, 5), "positive"),
    ((0.2, 0.3, 0.1, 0.1), r"at least a pixel \(boxes are in pixels, not normalised\)"),   # was tracked, "ok"
    ((10, 10, 1e-300, 20), "at least a pixel"),
    ((10, float("nan"), 5, 5), "finite"),
    ((10, 10, 5), "four"),
    ("abcd", "four"),
    ((500, 10, 20, 20), "outside"),
    ((-40, 10, 20, 20), "outside"),
    ((100, 10, 20, 20), "outside"),                              # touching the frame's edges: no pixel of it inside
    ((10, 100, 20, 20), "outside"),
    ((-20, 10, 20, 20), "outside"),
    ((10, -20, 20, 20), "outside"),
    ((0, 0, 5000, 5000), "larger than the 100x100 image"),       # took 16 s to initialise, 1e5 ran out of memory
    ((10**400, 10, 20, 20), "finite numbers .* past the float range"),   # numpy's OverflowError
    ((True, True, True, True), "not booleans"),                  # was tracked as a 1x1 box at (1, 1)
    ((10, 10, True, 20), "not booleans"),
    (np.ones(4, bool), "not booleans"),
    ([np.int64(10), 10, np.bool_(True), 20], "not booleans"),
])
def test_bad_boxes_raise_clear_errors(box, message):
    with pytest.raises(ValueError, match=message):
        Tracker().init(np.zeros((100, 100, 3), np.uint8), box)


def test_update_needs_init_and_a_frame_of_the_same_size():
    with pytest.raises(RuntimeError, match="init"):
        Tracker().update(np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(RuntimeError, match="init"):      # was AttributeError: no attribute 'pos'
        Tracker().box
    tracker = Tracker()
    tracker.init(np.zeros((100, 100, 3), np.uint8), (10, 10, 20, 20))
    with pytest.raises(ValueError, match="differs"):
        tracker.update(np.zeros((120, 100, 3), np.uint8))


def test_lost_flag_follows_the_pme_floor():
    images, truth = moving_target_sequence(frames=3)
    confident = _track(TrackerConfig.profile(lost_pme=1.0), images, truth[0])
    never_confident = _track(TrackerConfig.profile(lost_pme=1e9), images, truth[0])
    assert all(r.ok for r in confident) and not any(r.ok for r in never_confident)
    assert confident[0].pme == pytest.approx(never_confident[0].pme)


def test_config_validation_and_profiles():
    assert TrackerConfig.profile("paper").lambda1 == 5e-5
    assert TrackerConfig.profile("authors").context_interval == 4
    # ALGORITHM.md section A: the paper's lambda1, lambda2, f_c, penalties summing to 1 and beta_t; the code's values
    differing = ("lambda1", "context_lambda2", "context_interval", "context_penalty_total", "dim_floor")
    assert [getattr(TrackerConfig.profile("paper"), f) for f in differing] == [5e-5, 0.0625, 2, 1.0, 0.1]
    assert [getattr(TrackerConfig.profile("authors"), f) for f in differing] == [1e-4, 1 / 256, 4, 4.0, 0.3]
    assert TrackerConfig.profile("paper").dim_threshold == TrackerConfig.profile("authors").dim_threshold == 0.3
    kcc = TrackerConfig.profile("kcc")
    assert not (kcc.context_attention or kcc.dimensional_attention or kcc.spatiotemporal_attention)
    with pytest.raises(ValueError, match="unknown tracker profile"):
        TrackerConfig.profile("fastest")
    with pytest.raises(ValueError, match="unknown TrackerConfig field"):
        TrackerConfig.profile("paper", lamda1=1.0)
    with pytest.raises(ValueError, match="lambda1"):
        TrackerConfig(lambda1=0.0)
    with pytest.raises(ValueError, match="num_scales"):
        TrackerConfig(num_scales=32)
    with pytest.raises(ValueError, match="finite"):
        TrackerConfig(learning_rate=float("nan"))


def test_subcell_peak_halves_the_centre_error_on_a_moving_target():
    """Whole-cell peaks put the box up to half a cell (here about 1 px) off; the sub-cell peak finds it between."""
    images, truth = moving_target_sequence(frames=40, velocity=(2.0, 3.0))
    centres = truth[1:, :2] + truth[1:, 2:] / 2

    def mean_centre_error(subcell_peak: bool) -> float:
        boxes = np.array([r.box for r in _track(TrackerConfig.profile("paper", subcell_peak=subcell_peak),
                                                images, truth[0])])
        return float(np.mean(np.hypot(*(boxes[:, :2] + boxes[:, 2:] / 2 - centres).T)))

    whole, between = mean_centre_error(False), mean_centre_error(True)
    assert between < 0.8 and between < 0.7 * whole  # measured: 0.55 px against 1.07


def test_config_refuses_wrong_types_and_memory_bombs():
    """Overrides arrive over the network (start requests): wrong types and absurd sizes are refused up front."""
    assert TrackerConfig().profile_name == "authors" and TrackerConfig.profile().profile_name == "paper"
    for bad, message in [(dict(cell_size=1e-300), "cell_size must be int"), (dict(num_scales=True), "must be int"),
                         (dict(context_attention=1), "must be bool"), (dict(fixed_area=2.0**62), "<= 1e\\+06"),
                         (dict(scale_step=2.0**62), "scale_step must be <= 2"),
                         (dict(lambda1=10**400), "lambda1 must be finite"),             # an int past float range
                         (dict(hog_kernel_sigma=1e200), "hog_kernel_sigma must be <= 1e\\+06"),  # its square overflows
                         (dict(cn_output_sigma_factor=1e200), "cn_output_sigma_factor must be in \\[0.001, 1\\]")]:
        with pytest.raises(ValueError, match=message):
            TrackerConfig.profile("authors", **bad)
    assert TrackerConfig.profile("authors", lambda1=1).lambda1 == 1   # an int where a float is expected is fine


@pytest.mark.parametrize("field", ["learning_rate", "context_penalty_rate", "dim_learning_rate",
                                   "spatial_learning_rate", "hist_learning_rate", "likelihood_floor",
                                   "scale_learning_rate", "scale_min_visible", "motion_search_threshold",
                                   "lost_min_visible"])
def test_every_rate_and_fraction_is_refused_outside_0_to_1(field):
    """A rate or a fraction past 1 or under 0 means nothing (lost_min_visible=2 flags every frame lost, -1 none)."""
    for value in (-0.1, 1.5):
        with pytest.raises(ValueError, match=rf"TrackerConfig.{field} must be in \[0, 1\], got {value}"):
            TrackerConfig(**{field: value})
    for value in (0.0, 1.0):
        assert getattr(TrackerConfig(**{field: value}), field) == value


@pytest.mark.parametrize("field, value, message", [
    ("lambda1", 10**5000, "lambda1 must be finite"),        # str() raises past 4,300 digits: no field was named
    ("num_scales", 10**5000, "num_scales must be an int within its bounds"),
    ("cell_size", -10**5000, "cell_size must be an int within its bounds"),
    ("fast_fft", 10**5000, "fast_fft must be bool"),
    ("lambda1", Fraction(10**400), "lambda1 must be finite"),   # a Real: was OverflowError, not ValueError
], ids=["int-float", "int-int", "negative-int", "int-bool", "fraction-float"])    # pytest's own ids print them
def test_config_names_the_field_of_a_number_past_the_float_range(field, value, message):
    with pytest.raises(ValueError, match=f"TrackerConfig.{message}, got a number past the float range"):
        TrackerConfig.profile(**{field: value})
    assert TrackerConfig.profile(lambda1=Fraction(1, 10**4)).lambda1 == 1e-4


@pytest.mark.parametrize("overrides, message", [
    (dict(context_lambda2=-1.0), r"context_lambda2 must be in \[0, 1e\+06\]"),    # turned the model NaN, for good
    (dict(cn_poly_a=-1.0, cn_poly_b=0.5), r"cn_poly_a must be in \[0, 1000\]"),   # likewise
    (dict(hog_kernel_sigma=1e-6), "hog_kernel_sigma must be >= 0.01"),    # likewise
    (dict(hog_kernel_sigma=1e3), r"lambda1 \* hog_kernel_sigma\*\*4.* <= 1e\+06, got 5e\+07"),   # flat HOG responses:
    (dict(hog_kernel_sigma=2.0, lambda1=1e6), r"lambda1 \* hog_kernel_sigma\*\*4"),           # kcc's box froze
    (dict(hist_bins=3), "power of two up to 64"),                         # failed in init
    (dict(hist_bins=256), "power of two up to 64"),                       # 16.7 M bins: 9 s and 1 GB for 3 frames
    (dict(fixed_area=16.0), "the filter's cells"),                        # one cell: failed in init
    (dict(fixed_area=400.0), "the filter's cells\\) must be in \\[48, "),    # a one-cell response: the box froze
    (dict(cell_size=1, fixed_area=1e6), "the filter's cells"),            # 1e6 cells: 113 s and 3.3 GB
    (dict(num_scales=129, scale_step=1.1), "largest scale patch"),        # 446 times the target: 31 s, 1.2 GB
])
def test_config_refuses_combinations_the_tracker_cannot_run(overrides, message):
    with pytest.raises(ValueError, match=message):
        TrackerConfig.profile("paper", **overrides)


@pytest.mark.parametrize("overrides, message", [
    # float32 models: NaN filters, and the box sent to the search area's corner
    (dict(lambda1=1e-45), r"lambda1 must be in \[1e-12, 1e\+06\], got 1e-45"),
    (dict(lambda1=1e39), r"lambda1 must be in \[1e-12, 1e\+06\], got 1e\+39"),
    (dict(scale_lambda=1e39), r"scale_lambda must be in \[1e-12, 1e\+06\], got 1e\+39"),
    (dict(hog_output_sigma_factor=1e-300), r"hog_output_sigma_factor must be in \[0.001, 1\], got 1e-300"),
    (dict(cn_output_sigma_factor=1e-300), r"cn_output_sigma_factor must be in \[0.001, 1\], got 1e-300"),
    (dict(cn_poly_a=100.0, cn_poly_b=50.0), r"\(1 \+ cn_poly_a\) \*\* cn_poly_b.* must be <= 1e\+12, got 10\*\*100"),
    (dict(cn_poly_b=1e5), r"\(1 \+ cn_poly_a\) \*\* cn_poly_b.* must be <= 1e\+12, got 10\*\*3.01e\+04"),
    (dict(cn_poly_a=1e6, cn_poly_b=1.0), r"cn_poly_a must be in \[0, 1000\], got 1000000.0"),  # CN answered nothing
    (dict(cn_poly_b=0.0), r"cn_poly_b must be > 0, got 0.0"),                        # likewise
    # the kernel underflows on Color Names' small correlations: the filter all regularisation, a response of 0
    (dict(cn_poly_a=0.001, cn_poly_b=20.0),
     r"Color Names kernel's change .* must be >= 5e-05 \(lambda1, at most 0.0001\), or Color Names answers nothing; "
     r"got 10\*\*-37.9"),
    (dict(cn_poly_a=0.0, cn_poly_b=5.0), r"Color Names kernel's change .* got 10\*\*-9.3"),
    (dict(cn_poly_a=0.001, cn_poly_b=20.0, lambda1=1e-12), r"Color Names kernel's change .* must be >= 1e-12 "),
    (dict(context_challenge_floor=0.0), r"context_challenge_floor must be in \[0.001, 1000\], got 0.0"),  # 0/0
    # PME 0 on every frame, the box frozen
    (dict(context_challenge_floor=1e300), r"context_challenge_floor must be in \[0.001, 1000\]"),  # inf / inf penalties
    (dict(context_penalty_total=1e20), r"context_penalty_total must be in \[0, 1000\], got 1e\+20"),
    (dict(context_lambda2=1e38), r"context_lambda2 must be in \[0, 1e\+06\], got 1e\+38"),
    (dict(dim_floor=1e39), r"dim_floor must be in \[0.001, 10\], got 1e\+39"),
    (dict(dim_threshold=-1e39), r"dim_threshold must be in \[-10, 10\], got -1e\+39"),
    (dict(motion_gain=1e100), r"motion_gain must be in \[0, 100\], got 1e\+100"),
    (dict(motion_gain=-100.0), r"motion_gain must be in \[0, 100\], got -100.0"),           # PME down to 0.6
    (dict(scale_sigma_factor=1e-300), r"scale_sigma_factor must be in \[0.001, 1000\]"),   # divisions by zero
    # parts silently switched off
    (dict(hist_bins=1), r"hist_bins must be in \[2, 256\], got 1"),                  # a flat colour window
    (dict(likelihood_floor=5.0), r"likelihood_floor must be in \[0, 1\], got 5.0"),   # features times 5
    (dict(num_scales=3), r"num_scales must be in \[5, 129\], got 3"),                 # the centre scale alone
])
def test_config_refuses_values_that_broke_the_tracker(overrides, message):
    with pytest.raises(ValueError, match=message):
        TrackerConfig.profile("paper", **overrides)


def test_config_bounds_keep_the_profiles_and_their_ends():
    for name in PROFILES:
        TrackerConfig.profile(name)
    TrackerConfig.profile(lambda1=1e-12, scale_lambda=1e6, hog_output_sigma_factor=1e-3, cn_output_sigma_factor=1.0,
                          cn_poly_a=1e3, cn_poly_b=3.9, context_challenge_floor=1e-3, hist_bins=2,
                          likelihood_floor=1.0, num_scales=5, fixed_area=48.0 * 4**2)
    TrackerConfig.profile(context_penalty_total=1e3, context_lambda2=1e6, dim_floor=10.0, dim_threshold=-10.0,
                          motion_gain=100.0, scale_sigma_factor=1e3, context_challenge_floor=1e3)
    TrackerConfig.profile(lambda1=1e-12, hog_kernel_sigma=3e4)   # lambda1 * sigma**4 = 8.1e5: still tracks
    TrackerConfig.profile(context_penalty_total=0.0, context_lambda2=0.0, dim_floor=1e-3, dim_threshold=10.0,
                          motion_gain=0.0, scale_sigma_factor=1e-3)


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_the_heaviest_context_term_allowed_stays_finite():
    """At the ceilings of context_lambda2 and context_penalty_total a context patch is scaled up to a million
    times: float32 rounding made the Gaussian kernel's exponent hugely positive, exp overflowed ("overflow
    encountered in square") and the inf context energy zeroed the filters of 7-8 of the 31 HOG channels."""
    images, truth = moving_target_sequence(frames=8)
    for profile in ("paper", "authors"):
        tracker = Tracker(TrackerConfig.profile(profile, context_lambda2=1e6, context_penalty_total=1e3,
                                                context_interval=1))
        tracker.init(images[0], truth[0])
        results = [tracker.update(image) for image in images[1:]]
        assert np.abs(tracker.banks["hog"].model_filter_hat).max(axis=(1, 2)).min() > 0   # no channel switched off
        assert box_iou(results[-1].box, truth[-1]) > 0.6


def test_config_takes_numpy_scalars_as_the_python_values_they_are():
    """A sweep read from an array: np.int64 was refused as an int and np.float32 as a float, while np.float64
    passed (a float subclass). They are stored as Python values, so that dataclasses.asdict() stays JSON."""
    config = TrackerConfig.profile(cell_size=np.int64(4), num_scales=np.int32(33), lambda1=np.float32(1e-4),
                                   subcell_peak=np.bool_(False))
    assert config == TrackerConfig.profile(lambda1=float(np.float32(1e-4)), subcell_peak=False)
    assert [type(config.cell_size), type(config.lambda1), type(config.subcell_peak)] == [int, float, bool]
    json.dumps(dataclasses.asdict(config))
    for bad in (dict(num_scales=np.bool_(True)), dict(lambda1=np.bool_(True)), dict(cell_size=np.float64(4.0))):
        with pytest.raises(ValueError, match="must be (int|float)"):
            TrackerConfig.profile(**bad)


@pytest.mark.parametrize("target_hw", [(300, 6), (600, 12), (5, 250), (40, 40)])
def test_the_smallest_grid_still_has_a_response_to_move_in(target_hw):
    """At the floor of filter cells the cropped response keeps 3 cells a side, even for targets of 1:50 (at 36-40
    cells these had one, and a one-cell response never moves the box)."""
    image = np.zeros((1500, 1500), np.uint8)
    tracker = Tracker(TrackerConfig.profile(fixed_area=48.0 * 4**2, scale_estimation=False, colour_window=False))
    tracker.init(image, (600, 400, target_hw[1], target_hw[0]))
    assert tracker.grid.crop_cells >= 3


def test_init_refuses_a_box_whose_response_would_be_one_cell():
    """In a strip 67 times as long as high a long thin box's search area leaves one cell of response."""
    strip = texture(np.random.default_rng(2), (3, 200, 3), blur=1)
    tracker = Tracker()
    with pytest.raises(ValueError, match=r"response would be 1 cell\(s\) a side, under 3"):
        tracker.init(strip, (10, 1, 100, 1))
    with pytest.raises(RuntimeError, match="init"):
        tracker.update(strip)


def _dropouts(kind: str, frames: list[np.ndarray], box: np.ndarray) -> list[np.ndarray]:
    """Frames that show nothing of the target in place of `frames`: black, white and grey ones, clean or with a
    little noise (a video link's dropout), or the frames with the grey part of a corrupt frame over the target
    at `box` (a slice of rows, or a block)."""
    if kind == "blank":
        noise = np.random.default_rng(0).standard_normal(frames[0].shape)
        noisy_black = [np.clip(np.round(16 + sigma * noise), 0, 255).astype(np.uint8) for sigma in (1, 2)]
        return [np.full_like(frames[0], level) for level in (0, 0, 255, 128)] + noisy_black
    x, y, w, h = box.astype(int)
    columns = slice(None) if kind == "slice" else slice(x - 2 * w, x + 3 * w)
    corrupt = [frame.copy() for frame in frames]
    for frame in corrupt:
        frame[y - 2 * h:y + 3 * h, columns] = 128
    return corrupt


@pytest.mark.parametrize("profile", ["paper", "kcc"])
@pytest.mark.parametrize("kind", ["blank", "slice", "block"])
def test_a_camera_dropout_leaves_the_box_in_place_and_tracking_resumes(profile, kind):
    """Dropouts show nothing to track. Searched, the box walked off (on a blank frame half a cell a frame: the
    response window's two peaks on an even grid; on a corrupt one to the grey part's edges) and the model learnt
    a blank target. Now the box stays, not ok, and the target is found again after the dropout."""
    frames, boxes = moving_target_sequence(30, velocity=(0.5, 0.5))
    tracker = Tracker(TrackerConfig.profile(profile))
    tracker.init(frames[0], boxes[0])
    for frame in frames[1:10]:
        tracker.update(frame)
    before = tracker.box
    for dropout in _dropouts(kind, frames[10:16], boxes[10]):
        result = tracker.update(dropout)
        assert result.box == before and not result.ok and result.pme == 0.0
    assert all(box_iou(tracker.update(frame).box, box) > 0.5 for frame, box in zip(frames[16:], boxes[16:]))


def test_a_tiny_target_under_a_plain_sky_is_not_taken_for_a_partial_dropout():
    """A 6x6 bird or drone up to 12 grey levels under a noise-free sky: in means over 4x4 pixels it merged with
    the sky around it, the area around it passed for the grey part of a corrupt frame, and the box froze."""
    pattern = np.round(-12 * np.random.default_rng(0).uniform(0.3, 1.0, (6, 6, 1))).astype(np.int16)
    frames, boxes = [], []
    for i in range(40):
        frame = np.full((360, 480, 3), 200, np.int16)
        x, y = 150 + i, 150 + i // 2
        frame[y:y + 6, x:x + 6] += pattern
        frames.append(frame.astype(np.uint8))
        boxes.append((x, y, 6, 6))
    assert_follows(_track(TrackerConfig(), frames, boxes[0]), boxes)


def test_a_box_drawn_inside_a_plain_roof_is_searched_for_by_the_roof_edges():
    """A box inside a plain, noise-free roof (or a saturated one) shows a fill all around it from the first
    frame: it is no partial dropout, and the roof's edges in the search area lead the box as before."""
    road = texture(np.random.default_rng(7), (480, 720, 3), blur=4)
    frames, boxes = [], []
    for i in range(40):
        frame = road.copy()
        top, left = 150 + i, 100 + 3 * i
        frame[top:top + 130, left:left + 130] = (60, 60, 200)
        frames.append(frame)
        boxes.append((left + 35, top + 35, 60, 60))
    assert_follows(_track(TrackerConfig(), frames, boxes[0]), boxes)


def test_a_faint_target_in_fog_is_tracked_not_taken_for_a_dropout():
    """A target three grey levels above a flat background (fog, haze, an over-exposed sky) leaves its search area
    nearly one colour; taken for a dropout, the box stayed on the first frame's and was never ok."""
    rows, cols = np.mgrid[0:24, 0:24]
    pattern = np.round(3 * (0.6 + 0.4 * np.cos(cols / 3.0) * np.cos(rows / 4.0))).astype(np.uint8)
    frames, boxes = [], []
    for i in range(30):
        frame = np.full((480, 640), 128, np.uint8)
        x, y = 200 + 2 * i, 200 + i
        frame[y:y + 24, x:x + 24] += pattern
        frames.append(frame)
        boxes.append((x, y, 24, 24))
    assert_follows(_track(TrackerConfig(), frames, boxes[0]), boxes)


def test_a_target_that_outruns_its_search_area_over_plain_sky_is_still_searched_for():
    """A textured target speeding up over a flat sky leaves its search area blank; that area taken for a dropout
    froze the box before the motion search, which is there for such targets, could look ahead."""
    patch = texture(np.random.default_rng(3), (24, 32, 3), blur=1)
    frames, boxes, x, speed = [], [], 40.0, 4.0
    while x + 32 < 1600:
        frame = np.full((480, 1600, 3), (230, 200, 160), np.uint8)
        frame[220:244, int(x):int(x) + 32] = patch
        frames.append(frame)
        boxes.append((int(x), 220, 32, 24))
        speed, x = speed + 4, x + speed
    assert_follows(_track(TrackerConfig(), frames, boxes[0]), boxes)


def test_an_init_refused_keeps_the_target_already_followed():
    """A refused re-init, whatever the reason, leaves the tracker as it was: the one-cell refusal used to drop
    the running target (box reported as the refused one, update asking for init)."""
    frames, boxes = moving_target_sequence(6)
    strip = texture(np.random.default_rng(2), (3, 200, 3), blur=1)
    tracker = Tracker()
    tracker.init(frames[0], boxes[0])
    tracker.update(frames[1])
    followed = tracker.box
    for frame, box, message in [(strip, (10, 1, 100, 1), "response would be 1 cell"),
                                (frames[2], (-500, -500, 20, 20), "outside")]:
        with pytest.raises(ValueError, match=message):
            tracker.init(frame, box)
        assert tracker.box == followed
    assert box_iou(tracker.update(frames[2]).box, boxes[2]) > 0.5


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
@pytest.mark.parametrize("value", [np.nan, np.inf, 0.0], ids=["nan", "inf", "flat"])
def test_a_response_without_a_peak_leaves_the_box_in_place_and_not_ok(monkeypatch, value):
    """np.argmax of a NaN map is its first NaN and of a flat one its first cell: the box jumped by the whole search
    radius up and left. Now it stays, with PME 0, not ok even under a floor of 0."""
    from tacf.correlator import CorrelatorBank

    images, truth = moving_target_sequence(frames=5)
    tracker = Tracker(TrackerConfig.profile(lost_pme=0.0))
    tracker.init(images[0], truth[0])
    tracker.update(images[1])
    centre = np.array(tracker.box[:2]) + np.array(tracker.box[2:]) / 2
    with monkeypatch.context() as patch:
        patch.setattr(CorrelatorBank, "response", lambda self, z, *args: np.full(z.shape[-2:], value, np.float32))
        result = tracker.update(images[2])
    assert np.array(result.box[:2]) + np.array(result.box[2:]) / 2 == pytest.approx(centre)
    assert result.pme == 0.0 and not result.ok
    assert box_iou(tracker.update(images[3]).box, truth[3]) > 0.5  # and tracks on


@pytest.mark.parametrize("tracker_class", [Tracker, Staple])
@pytest.mark.parametrize("box", [(-30, 100, 40, 60), (310, 100, 40, 60), (150, -20, 40, 30), (150, 230, 40, 30)],
                         ids=["left", "right", "top", "bottom"])
def test_a_box_with_its_centre_outside_the_frame_stays_put_on_identical_frames(box, tracker_class):
    """init accepts a box that overlaps the frame; the first update clipped its centre into the frame, a 10 px
    jump on identical frames (Staple's until 2026-12-05). (Its size may drift by a pixel: the scale samples there are
    mostly replicated border.)"""
    image = texture(np.random.default_rng(4), (240, 320, 3), blur=2)
    tracker = tracker_class()
    tracker.init(image, box)
    centre = np.array(box[:2]) + np.array(box[2:]) / 2
    for _ in range(5):
        result = tracker.update(image)
        assert np.array(result.box[:2]) + np.array(result.box[2:]) / 2 == pytest.approx(centre, abs=1.5)
        assert result.ok


@pytest.mark.parametrize("box", [(10, 137, 40, 138), (275, 10, 276, 40), (10, -137, 40, 138)],
                         ids=["as-tall-by-the-last-row", "as-wide-by-the-last-column", "as-tall-by-the-first-row"])
def test_a_box_the_size_of_the_frame_overlapping_it_by_one_line_is_tracked(box):
    """init accepts such a box; the dropout check then looked at an area wholly below (or right of) the frame,
    empty, and every update raised cv2.error."""
    image = texture(np.random.default_rng(5), (138, 276, 3), blur=2)
    tracker = Tracker()
    tracker.init(image, box)
    for _ in range(3):
        tracker.update(image)


def test_blank_frames_leave_the_scale_alone():
    """A frame without gradients (blank, or a uniform occluder over the target) answers 0 at every scale; the
    first maximum of that was the largest scale, so each such frame grew the box 1.6 times, for good."""
    images, truth = moving_target_sequence(frames=30, velocity=(0.0, 1.0))
    blank = np.zeros_like(images[0])
    tracker = Tracker()
    tracker.init(images[0], truth[0])
    results = [tracker.update(image) for image in images[1:10] + [blank] * 3 + images[13:]]
    assert [r.scale for r in results[8:12]] == [results[8].scale] * 4
    assert box_iou(results[-1].box, truth[-1]) > 0.6


CORNERS = {"top-left": (-1, -1), "top-right": (-1, 1), "bottom-left": (1, -1), "bottom-right": (1, 1)}


@pytest.mark.parametrize("tracker_type", [Tracker, Staple])
@pytest.mark.parametrize("corner", CORNERS)
def test_a_target_leaving_through_a_corner_does_not_grow_the_box(tracker_type, corner):
    """Beyond a corner the scale patches are one flat colour, the corner pixel repeated, with no fHOG features:
    the smaller scales answered less and the box grew up to 5.9 times in 20 frames as the target left (Staple's
    9 times), ok all along (docs/decisions.md). Now the scale rests while the box is mostly beyond the frame."""
    for target in ((16, 20), (30, 24)):
        images, truth = leaving_sequence(CORNERS[corner], target=target)
        tracker = tracker_type()
        tracker.init(images[0], truth[0])
        grown = [r.scale for r in map(tracker.update, images[1:]) if r.ok]
        assert max(grown) < 1.5, (target, max(grown))


def _in_view(box, frame_shape) -> float:
    x, y, w, h = box
    return visible_fraction((y + h / 2, x + w / 2), (h, w), frame_shape)


def test_a_box_left_beyond_the_frame_is_not_ok():
    """Once the target has left, the search follows the background at the frame's edge with PMEs of 20-43, over
    the lost floor: a box all but wholly beyond the frame was ok, and a consumer pointing a gimbal at ok boxes
    pointed it off the frame. Now a box under lost_min_visible in view is not ok; one that drifts back onto the
    background in view still is (through the top-right and bottom-left corners here). While the target is half
    in view or more, it is followed and ok."""
    beyond = []
    for direction in list(CORNERS.values()) + [(0, 1), (1, 0)]:
        for target in ((16, 20), (30, 24)):
            images, truth = leaving_sequence(direction, target=target)
            tracker = Tracker()
            tracker.init(images[0], truth[0])
            results = [tracker.update(image) for image in images[1:]]
            assert all(r.ok for r, box in zip(results, truth[1:]) if _in_view(box, images[0].shape) >= 0.5)
            beyond += [r for r in results if _in_view(r.box, images[0].shape) < 0.1]
    assert len(beyond) >= 20 and not any(r.ok for r in beyond), [(r.ok, round(r.pme)) for r in beyond]


def test_a_still_target_stays_put_with_whole_cell_peaks():
    """A target that does not move is found where it was: every box of a still sequence is the first one."""
    images, boxes = moving_target_sequence(frames=6, velocity=(0.0, 0.0))
    results = _track(TrackerConfig.profile("authors", context_attention=False, subcell_peak=False), images, boxes[0])
    assert all(result.box == pytest.approx(tuple(boxes[0]), abs=0.5) for result in results)


def test_locate_then_learn_gives_the_boxes_of_update():
    """update() is locate() then learn(): split, the boxes are the same, whether learn() is called after each
    locate() or left to the next locate(); learn() twice learns once."""
    images, boxes = moving_target_sequence(frames=12)
    expected = _track(TrackerConfig.profile("authors", context_interval=2), images, boxes[0])
    split = Tracker(TrackerConfig.profile("authors", context_interval=2))
    split.init(images[0], boxes[0])
    results = []
    for number, image in enumerate(images[1:]):
        results.append(split.locate(image))
        if number % 3:  # every third frame leaves learning to the next locate()
            split.learn()
            split.learn()
    assert results == expected
    with pytest.raises(RuntimeError, match="init"):
        Tracker().locate(images[0])

_HEAP_REUSE_CHECK = """
import ctypes, sys
if sys.argv[1] == "tracker":
    from tacf import Tracker
    Tracker()
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
block = libc.malloc(3 << 20)
libc.free(block)
again = libc.malloc(3 << 20)
print("reused" if again == block else "mapped anew")
"""


def test_tracker_keeps_freed_memory_for_reuse():
    """On glibc a Tracker raises malloc's mmap/trim thresholds once (tacf/allocator.py): a 3 MB block freed and
    asked for again then comes back from the heap at the same address, where a fresh process maps it anew."""
    import platform
    import subprocess
    import sys

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("the allocator tuning applies to glibc only")

    def run(mode):
        return subprocess.run([sys.executable, "-c", _HEAP_REUSE_CHECK, mode], capture_output=True, text=True,
                              check=True).stdout.strip()

    assert run("plain") == "mapped anew"
    assert run("tracker") == "reused"


_ONE_CORE_CHECK = """
import sys, time
sys.path.insert(0, sys.argv[1])
from synthetic import moving_target_sequence
from tacf import Tracker, TrackerConfig
images, truth = moving_target_sequence(frames=60, size=(480, 640), target=(60, 48))
for profile in ("paper", "authors"):
    tracker = Tracker(TrackerConfig.profile(profile))
    tracker.init(images[0], truth[0])
    cpu, wall = time.process_time(), time.perf_counter()
    for image in images[1:]:
        tracker.update(image)
    print(profile, (time.process_time() - cpu) / (time.perf_counter() - wall))
"""


def test_a_tracker_keeps_to_one_core():
    """A stream costs one core: nothing on the per-frame path may wake a threaded BLAS, whose idle threads spin
    on the other cores (one np.tensordot on the context frames once doubled the tracker's CPU time for nothing,
    taking the second core from whatever ran beside it). Process CPU time over wall time, in a fresh process so
    that no other test's threads count."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: a second thread could not show")
    out = subprocess.run([sys.executable, "-c", _ONE_CORE_CHECK, str(Path(__file__).parent)], capture_output=True,
                         text=True, check=True).stdout.split()
    cores = dict(zip(out[::2], map(float, out[1::2])))
    assert set(cores) == {"paper", "authors"} and max(cores.values()) < 1.3, cores


def test_fast_context_cuts_the_four_context_patches_from_one_sample():
    """Where the grid is the image's own (normalised area = search area, no resize), the four windows cut from the
    covering sample hold the separate context patches' fHOG, border cells aside (they see the pixels beyond)."""
    image = texture(np.random.default_rng(5), (320, 360, 3), blur=2)
    box = (100, 80, 32, 32)  # padding 3: a 128 x 128 search area, the normalised one with fixed_area = 128^2
    trackers = {}
    for fast in (True, False):
        tracker = Tracker(TrackerConfig.profile("authors", fast_context=fast, fast_fft=False, fixed_area=128.0**2))
        tracker.init(image, box)
        trackers[fast] = tracker
    assert trackers[True].grid.filter_hw == (32, 32) and trackers[True].areas.resize_factor == 1.0
    cut, separate = (trackers[fast]._context_features(image) for fast in (True, False))
    assert cut.shape == separate.shape == (4, 31, 32, 32)
    inner = (slice(None), slice(None), slice(2, -2), slice(2, -2))
    np.testing.assert_allclose(cut[inner], separate[inner], rtol=1e-5, atol=1e-6)
    assert not np.allclose(cut[0], cut[1])  # four different places


_WARMED_FORK_SERVER_CHECK = """
import json, sys
sys.path.insert(0, sys.argv[1])
from numba.core.registry import CPUDispatcher
import tacf_service.warm  # what the service's fork server runs before it forks a worker
from synthetic import moving_target_sequence
from tacf import Tracker, TrackerConfig
from tacf.config import PROFILES

def compiled_signatures():
    return {f"{name}.{attribute}": len(value.signatures) for name, module in list(sys.modules.items())
            if name.startswith("tacf") for attribute, value in vars(module).items()
            if isinstance(value, CPUDispatcher)}

warmed = compiled_signatures()
for gray in (False, True):
    images, truth = moving_target_sequence(frames=8, size=(180, 200), gray=gray)
    for profile in PROFILES:
        tracker = Tracker(TrackerConfig.profile(profile))
        tracker.init(images[0], truth[0])
        for image in images[1:]:
            tracker.update(image)
tracked = compiled_signatures()
print(json.dumps([sorted(name for name, count in warmed.items() if count),
                  sorted(name for name, count in tracked.items() if count != warmed[name])]))
"""


def test_the_fork_server_compiles_every_loop_a_session_calls():
    """Workers are forked from a server that ran tacf_service.warm: every numba loop a session calls must be
    compiled there (or loaded from numba's cache), or the session's first frame compiles it while frames queue.
    The colour lookup was left out: its first box came 0.4-0.6 s late and 16 frames were dropped. In a fresh
    process, tracking colour and gray frames under every profile after the warm-up compiles nothing new."""
    import subprocess
    import sys
    from pathlib import Path

    out = subprocess.run([sys.executable, "-c", _WARMED_FORK_SERVER_CHECK, str(Path(__file__).parent)],
                         capture_output=True, text=True, check=True).stdout
    warmed, compiled_later = json.loads(out)
    assert compiled_later == [], f"compiled at a session's frames, not in the fork server: {compiled_later}"
    assert "tacf.colour._per_pixel" in warmed and "tacf.features.fhog._fhog_images" in warmed, warmed
