"""The three attentions and the response helpers, on hand-made maps."""
import numpy as np
import pytest

from tacf.attention import ContextualAttention, DimensionalAttention, SpatiotemporalAttention, context_offsets, pme
from tacf.attention.contextual import median
from tacf.attention.spatiotemporal import add_motion, attention_map, to_response_origin
from tacf.response import (crop_centre, fuse, fusion_coefficients, fusion_weight, peak_offset, subcell_peak_offset,
                           upsample)


def test_pme_on_a_hand_made_map():
    response = np.zeros((4, 4))
    response[1, 2] = 4.0
    # median 0, mean squared deviation 16 / 16 = 1, (max - median)^2 = 16
    assert pme(response) == pytest.approx(16.0)
    response += 3.0  # invariant to an offset
    assert pme(response) == pytest.approx(16.0)
    assert pme(np.ones((5, 5))) == 0.0


@pytest.mark.parametrize("shape", [(101, 101), (25, 24), (1,), (2,), (7, 3)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_is_numpy_s(shape, dtype):
    values = np.random.default_rng(sum(shape)).standard_normal(shape).astype(dtype)
    values.flat[0] = values.flat[-1]  # a tie
    assert median(values) == np.median(values)
    assert median(values).dtype == np.median(values).dtype


def test_pme_of_a_response_with_nan_is_zero():
    response = np.ones((5, 5))
    response[2, 2], response[0, 0] = 5.0, np.nan
    assert pme(response) == 0.0


def test_sharper_peak_has_higher_pme():
    grid = np.arange(-10, 11)
    distance2 = grid[:, None] ** 2 + grid[None, :] ** 2
    assert pme(np.exp(-distance2 / 2.0)) > pme(np.exp(-distance2 / 50.0))


def test_penalties_follow_the_challenge_factors():
    attention = ContextualAttention(interval=4, penalty_total=4.0, challenge_floor=0.3, penalty_rate=1.0,
                                    lambda2=1 / 256)
    attention.update_penalties(object_pme=10.0, context_pmes=np.array([10.0, 5.0, 1.0, 0.0]))
    challenge = np.array([1.0, 0.5, 0.3, 0.3])  # the last two floored at 0.3
    np.testing.assert_allclose(attention.penalties, 4 * challenge**2 / np.sum(challenge**2))
    assert attention.penalties.sum() == pytest.approx(4.0)
    np.testing.assert_allclose(attention.feature_scales(), attention.penalties / 16)


def test_penalties_are_smoothed_across_context_frames():
    attention = ContextualAttention(4, 1.0, 0.3, penalty_rate=0.2, lambda2=0.0625)
    np.testing.assert_allclose(attention.penalties, 0.25)
    attention.update_penalties(1.0, np.array([1.0, 0.3, 0.3, 0.3]))
    fresh = np.array([1.0, 0.09, 0.09, 0.09]) / 1.27
    np.testing.assert_allclose(attention.penalties, 0.2 * fresh + 0.8 * 0.25)


def test_context_frames_and_offsets():
    attention = ContextualAttention(4, 4.0, 0.3, 0.2, 1 / 256)
    assert [k for k in range(1, 14) if attention.is_context_frame(k)] == [1, 5, 9, 13]
    np.testing.assert_array_equal(context_offsets(np.array([20.0, 10.0])),
                                  [[-20, 0], [0, -10], [20, 0], [0, 10]])


def test_dimensional_gating():
    attention = DimensionalAttention(channels=3, threshold=0.3, floor=0.1, learning_rate=1.0)
    attention.update(np.array([2.0, 0.9, 0.1]), np.array([0.08, 0.036, 0.004]))
    # z = max + mean = 2.08, 0.936, 0.104; mean-1 normalisation: z * 3 / 3.12
    z = np.array([2.08, 0.936, 0.104]) * 3 / 3.12
    gated = np.maximum(z - 0.3, 0) + 0.1
    np.testing.assert_allclose(attention.weights, 3 * gated / gated.sum())
    assert attention.weights[2] < attention.weights[1] < attention.weights[0]


def test_dimensional_weights_move_slowly():
    attention = DimensionalAttention(channels=2, threshold=0.3, floor=0.3, learning_rate=0.022)
    attention.update(np.array([1.0, 0.0]), np.array([1 / 16, 0.0]))
    assert abs(attention.weights[0] - 1.0) < 0.05 and attention.weights.mean() == pytest.approx(1.0)


def test_spatial_map_is_largest_at_the_windowed_peak():
    response = np.zeros((9, 9))
    response[8, 8] = 1.0  # zero displacement sits at (H-1, W-1)
    window = to_response_origin(np.outer(np.hanning(9), np.hanning(9)))
    assert window[8, 8] == pytest.approx(1.0)
    spatial_map = attention_map(response, window)
    assert np.unravel_index(np.argmax(spatial_map), spatial_map.shape) == (8, 8)
    assert spatial_map.min() == pytest.approx(0.5)  # below the mean: exp(0) - 0.5


def test_motion_term_adds_a_copy_shifted_along_the_motion():
    spatial_map = np.zeros((10, 10))
    spatial_map[0, 0] = 1.0
    moved = add_motion(spatial_map, displacement=np.array([0.0, 2.0]), target_hw=np.array([10.0, 10.0]),
                       gain=2.0)
    gamma = 2 * 2 / np.hypot(10, 10)
    shift = int(np.floor(gamma * 10 + 0.5))
    assert shift == 3 and moved[0, shift] == pytest.approx(gamma)
    np.testing.assert_array_equal(add_motion(spatial_map, np.zeros(2), np.ones(2) * 10, 2.0), spatial_map)


def test_motion_term_stops_at_the_edge_of_the_map_instead_of_wrapping_behind_the_motion():
    """gamma_t times the grid is 7 of 10 columns here: the code's roll puts the copy at column 7, which in the
    response's circular layout is 3 columns *against* the motion; stopped at the edge it stays 4 ahead."""
    spatial_map = np.zeros((10, 10))
    spatial_map[0, 0] = 1.0
    motion = dict(displacement=np.array([0.0, 5.0]), target_hw=np.array([10.0, 10.0]), gain=2.0)
    gamma = 2 * 5 / np.hypot(10, 10)
    assert add_motion(spatial_map, **motion, wraps=True)[0, 7] == pytest.approx(gamma)
    stopped = add_motion(spatial_map, **motion)
    assert stopped[0, 4] == pytest.approx(gamma) and stopped[0, 7] == 0
    backwards = add_motion(spatial_map, np.array([0.0, -5.0]), motion["target_hw"], 2.0)
    assert backwards[0, -4] == pytest.approx(gamma)


@pytest.mark.parametrize("rate", [0.25, 1.0])   # not 0.5, at which the EMA's two weights could be swapped unseen
def test_spatial_map_ema(rate):
    attention = SpatiotemporalAttention(learning_rate=rate, motion_gain=2.0)
    window = np.ones((5, 5))
    first = np.zeros((5, 5)); first[4, 4] = 1
    second = np.zeros((5, 5)); second[0, 0] = 1
    attention.keep(attention.propose(first, window, None, np.ones(2)))
    attention.propose(np.ones((5, 5)), window, None, np.ones(2))  # proposed, not kept: no effect
    combined = attention.propose(second, window, None, np.ones(2))
    np.testing.assert_allclose(combined, (1 - rate) * attention_map(first, window)
                               + rate * attention_map(second, window))     # rate 1, the default: this frame's map


def test_crop_centres_the_zero_displacement():
    response = np.zeros((12, 10))
    response[11, 9] = 1.0  # displacement (-1, -1) in the corner origin: the label peak
    cropped = crop_centre(response, 5)
    assert cropped[2, 2] == 1.0
    np.testing.assert_array_equal(peak_offset(cropped), [0, 0])
    response = np.zeros((12, 10))
    response[1, 0] = 1.0  # two rows down, one column right of the label peak
    np.testing.assert_array_equal(peak_offset(crop_centre(response, 7)), [2, 1])


def test_peak_tie_break_is_column_major():
    response = np.zeros((5, 5))
    response[0, 3] = response[3, 1] = 1.0
    np.testing.assert_array_equal(peak_offset(response), [1, -1])  # (3, 1) comes first by columns


def _with(value, at):
    """A peak two cells right of the centre, and value at `at`."""
    response = np.exp(-np.add.outer(np.arange(-3, 4) ** 2, np.arange(-5, 2) ** 2) / 4.0)
    response[at] = value
    return response


@pytest.mark.parametrize("response", [np.zeros((7, 7)), np.full((7, 7), np.nan), _with(np.nan, (5, 1)),
                                      _with(-np.inf, (0, 0)), _with(np.inf, (3, 4))],
                         ids=["flat", "all-nan", "one-nan", "minus-inf", "inf-beside-peak"])
def test_a_response_without_a_peak_gives_no_move(response):
    """A response with a NaN or an infinity is broken, a flat one finds nothing: no move from either peak function.
    np.argmax took the first NaN, or the first cell of a flat map: a move to the corner."""
    np.testing.assert_array_equal(peak_offset(response), [0, 0])
    np.testing.assert_array_equal(subcell_peak_offset(response), [0, 0])


def test_fusion_prefers_the_confident_response():
    grid = np.arange(-10, 11)
    sharp = np.exp(-(grid[:, None] ** 2 + grid[None, :] ** 2) / 4.0)
    rng = np.random.default_rng(0)
    noisy = rng.random((21, 21))
    assert fusion_weight(sharp) > fusion_weight(noisy)
    fused = fuse([sharp, noisy])
    np.testing.assert_array_equal(peak_offset(fused), [0, 0])
    assert fusion_weight(np.zeros((5, 5))) == 0.0


def test_fusion_divides_each_response_by_its_peak():
    """sum_M p_M R_M / max(R_M), the p_M summing to 1: a response of a thousand times the values (HOG's and Color
    Names' differ by orders of magnitude) weighs no more; of two copies, one scaled, the fusion is the map over its
    peak."""
    rng = np.random.default_rng(2)
    hog, colour_names = rng.random((9, 9)), rng.random((9, 9))
    weights = np.array([fusion_weight(hog), fusion_weight(colour_names)])
    weights /= weights.sum()
    np.testing.assert_allclose(fuse([hog, 1000 * colour_names]),
                               weights[0] * hog / hog.max() + weights[1] * colour_names / colour_names.max())
    np.testing.assert_allclose(fuse([hog, 1000 * hog]), hog / hog.max())


@pytest.mark.parametrize("true_offset", [(0.0, 0.0), (0.3, -0.2), (-0.45, 0.4), (2.25, -1.7)])
def test_subcell_peak_finds_a_peak_between_cells(true_offset):
    grid = np.arange(-7, 8, dtype=float)
    rows, cols = np.meshgrid(grid, grid, indexing="ij")
    response = np.exp(-((rows - true_offset[0]) ** 2 + (cols - true_offset[1]) ** 2) / (2 * 1.5**2))
    np.testing.assert_array_equal(peak_offset(response), np.round(true_offset))  # whole cells only
    np.testing.assert_allclose(subcell_peak_offset(response), true_offset, atol=0.1)


def test_subcell_peak_on_the_border_is_refined_only_along_it():
    response = np.zeros((5, 5))
    response[0, 2], response[1, 2], response[0, 3] = 1.0, 0.5, 0.9  # top row: no neighbour above
    # rows: none (whole cell, -2); columns: 0, 1, 0.9 around the peak -> vertex at 0.5 * 0.9 / 1.1 = +0.409
    np.testing.assert_allclose(subcell_peak_offset(response), [-2.0, 0.409], atol=1e-3)


def test_upsampling_commutes_with_fusion():
    """The tracker refines the peak on the cell-level fused map, which the upsampled fused map is drawn from."""
    rng = np.random.default_rng(1)
    cells = [rng.random((11, 11)).astype(np.float32) for _ in range(2)]
    upsampled = [upsample(c, 45) for c in cells]
    coefficients = fusion_coefficients(upsampled)
    np.testing.assert_allclose(upsample(fuse(cells, coefficients), 45), fuse(upsampled), rtol=1e-5, atol=1e-6)
