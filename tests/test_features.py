"""Tests for the fHOG and Color Names feature extractors (ALGORITHM.md 4.1-4.3)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tacf.features import color_names, fhog, fhog_batch

SEQUENCES = Path(__file__).resolve().parents[2] / "shared" / "data" / "sequences"
TEXTURE = 0.2357
CN_BLACK, CN_BLUE, CN_GREEN, CN_RED, CN_WHITE = 0, 1, 4, 8, 9


def random_image(shape, seed=0):
    return np.random.default_rng(seed).random(shape, dtype=np.float32)


# --------------------------------------------------------------------------------------------------------
# A slow fHOG written pixel by pixel from ALGORITHM.md 4.1, independent of the vectorised implementation.
# --------------------------------------------------------------------------------------------------------

def _reference_bin(gx: np.float32, gy: np.float32) -> int:
    """Hard orientation bin as the C code computes it: acos table, float32 arithmetic."""
    f32 = np.float32
    pi = f32(3.14159265)
    magnitude = f32(math.sqrt(f32(gx * gx) + f32(gy * gy)))
    inverse = min(f32(1.0) / magnitude, f32(1e10)) if magnitude > 0 else f32(1e10)
    cosine = f32(f32(gx * inverse) * f32(10000))
    if gy < 0:
        cosine = -cosine
    i = int(cosine)  # truncation toward zero
    theta = pi if i <= -10000 else f32(0.0) if i >= 10000 else f32(math.acos(float(f32(i) / f32(10000))))
    theta = min(theta, f32(pi - f32(1e-6)))
    if gy < 0:
        theta = f32(theta + pi)
    o = int(f32(f32(f32(theta * f32(18)) / f32(f32(2) * pi)) + f32(0.5)))
    return o % 18


def reference_fhog(image: np.ndarray, cell: int = 4, clip: float = 0.2) -> np.ndarray:
    image = np.asarray(image, np.float32)
    if image.ndim == 2:
        image = image[:, :, None]
    h, w, channels = image.shape
    rows, cols = h // cell, w // cell
    hist = np.zeros((18, rows, cols))
    for r in range(rows * cell):
        for c in range(cols * cell):
            best = None
            for ch in range(channels):
                img = image[:, :, ch]
                gx = (img[r, c + 1] - img[r, c - 1]) * np.float32(0.5) if 0 < c < w - 1 else \
                    (img[r, 1] - img[r, 0] if c == 0 else img[r, w - 1] - img[r, w - 2])
                gy = (img[r + 1, c] - img[r - 1, c]) * np.float32(0.5) if 0 < r < h - 1 else \
                    (img[1, c] - img[0, c] if r == 0 else img[h - 1, c] - img[h - 2, c])
                squared = np.float32(gx * gx) + np.float32(gy * gy)
                if best is None or squared > best[0]:
                    best = (squared, gx, gy)
            squared, gx, gy = best
            o = _reference_bin(gx, gy)
            m = math.sqrt(squared) / cell**2
            u, v = (c + 0.5) / cell - 0.5, (r + 0.5) / cell - 0.5
            for cy, wy in ((math.floor(v), 1 - (v - math.floor(v))), (math.floor(v) + 1, v - math.floor(v))):
                for cx, wx in ((math.floor(u), 1 - (u - math.floor(u))), (math.floor(u) + 1, u - math.floor(u))):
                    if 0 <= cy < rows and 0 <= cx < cols:
                        hist[o, cy, cx] += wy * wx * m
    for border in (0, rows - 1):
        hist[:, border, :] *= 8 / 7
    for border in (0, cols - 1):
        hist[:, :, border] *= 8 / 7
    insensitive = hist[:9] + hist[9:]
    energy = (insensitive ** 2).sum(axis=0)
    eps = 1e-4 / 4 / cell**4
    out = np.zeros((31, rows, cols))
    for y in range(rows):
        for x in range(cols):
            normalisers = []
            for by, bx in ((y, x), (y - 1, x), (y, x - 1), (y - 1, x - 1)):  # block top-left corners
                by, bx = min(max(by, 0), rows - 2), min(max(bx, 0), cols - 2)
                block = energy[by:by + 2, bx:bx + 2].sum()
                normalisers.append(1 / math.sqrt(block + eps))
            for k, n in enumerate(normalisers):
                t1 = np.minimum(hist[:, y, x] * n, clip)
                t2 = np.minimum(insensitive[:, y, x] * n, clip)
                out[:18, y, x] += 0.5 * t1
                out[18:27, y, x] += 0.5 * t2
                out[27 + k, y, x] = TEXTURE * t1.sum()
    return out


# --------------------------------------------------------------------------------------------------------
# fHOG
# --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(8, 8), (13, 17), (230, 174, 3), (41, 30, 3), (64, 48, 1), (21, 22, 2)])
def test_fhog_shape_dtype_layout(shape):
    out = fhog(random_image(shape))
    assert out.shape == (31, shape[0] // 4, shape[1] // 4)
    assert out.dtype == np.float32
    assert out.flags.c_contiguous


def test_fhog_other_cell_size():
    assert fhog(random_image((30, 50, 3)), cell_size=6).shape == (31, 5, 8)


def test_fhog_rejects_too_small_and_bad_rank():
    with pytest.raises(ValueError):
        fhog(random_image((3, 40)))
    with pytest.raises(ValueError):
        fhog(random_image((8, 8, 3, 1)))


@pytest.mark.parametrize("shape", [(4, 40), (7, 40, 3), (40, 5)])
def test_fhog_single_cell_row_or_column_is_finite_and_bounded(shape):
    # Thin DSST scale patches can be one cell high; the C code has no proper normaliser there.
    image = np.zeros(shape, np.float32)
    image[:, shape[1] // 2:] = 1.0  # a vertical step edge
    image += 0.1 * random_image(shape, seed=11)
    out = fhog(image)
    assert out.shape == (31, shape[0] // 4, shape[1] // 4)
    assert np.isfinite(out).all() and out.min() >= 0 and out[:27].max() <= 0.4 + 1e-6
    if shape[1] >= 8:
        assert out[0].sum(axis=0).argmax() in (shape[1] // 8 - 1, shape[1] // 8)


@pytest.mark.parametrize("shape", [(9, 14), (12, 16, 3), (15, 10, 2)])
def test_fhog_matches_pixel_by_pixel_reference(shape):
    image = random_image(shape, seed=3)
    np.testing.assert_allclose(fhog(image), reference_fhog(image), rtol=1e-5, atol=1e-6)


def test_fhog_matches_reference_with_other_cell_size():
    image = random_image((14, 19, 3), seed=4)
    np.testing.assert_allclose(fhog(image, cell_size=3, clip=0.3), reference_fhog(image, cell=3, clip=0.3),
                               rtol=1e-5, atol=1e-6)


@pytest.mark.data
def test_fhog_matches_reference_on_real_frame_patch():
    frames = sorted(SEQUENCES.glob("UAV123_10fps/boat5/img/*.jpg"))
    if not frames:
        pytest.skip("shared sequences not available")
    import cv2
    patch = cv2.imread(str(frames[0]))[300:342, 400:437]  # 42x37: a real, textured colour patch
    image = cv2.cvtColor(patch, cv2.COLOR_BGR2RGB).astype(np.float32) / 255
    np.testing.assert_allclose(fhog(image), reference_fhog(image), rtol=1e-5, atol=1e-6)


def test_fhog_matches_reference_on_integer_image_with_ties_and_boundaries():
    # Integer steps give many exact orientation-bin boundaries (gx == 0) and equal channel magnitudes.
    rng = np.random.default_rng(7)
    image = rng.integers(0, 3, size=(16, 12, 3)).astype(np.float32)
    np.testing.assert_allclose(fhog(image), reference_fhog(image), rtol=1e-5, atol=1e-6)


def test_fhog_non_negative_and_bounded_by_truncation():
    for clip in (0.2, 0.1):
        out = fhog(random_image((60, 44, 3), seed=1) * 255, clip=clip)
        assert out.min() >= 0
        # Orientation channels: 0.5 * sum of 4 values each <= clip.
        assert out[:27].max() <= 2 * clip + 1e-6
        # Texture channels: 0.2357 * sum of 18 values each <= clip.
        assert out[27:].max() <= TEXTURE * 18 * clip + 1e-6


def test_fhog_uniform_image_is_zero():
    assert not fhog(np.full((40, 32, 3), 0.7, np.float32)).any()


def test_fhog_hand_computed_ramp():
    # Value = column index: gx = 1 everywhere (central and one-sided alike), gy = 0, so theta = 0 (bin 0).
    # Each cell of the 2x2 grid gets row and column weight 3.5 each: 3.5 * 3.5 / 16 * (8/7)^2 = 1.
    # Insensitive energy 1 per cell; one block: n = 1 / sqrt(4 + eps), so R * n = 0.5, clipped to 0.2.
    ramp = np.tile(np.arange(8, dtype=np.float32), (8, 1))
    out = fhog(ramp)
    expected = np.zeros((31, 2, 2), np.float32)
    expected[0] = expected[18] = 0.5 * 4 * 0.2
    expected[27:] = TEXTURE * 0.2
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-7)
    # Without clipping the normalised value is 1 / sqrt(4 + 1e-4 / 1024) per normaliser.
    n = 1 / math.sqrt(4 + 1e-4 / 1024)
    loose = fhog(ramp, clip=1.0)
    np.testing.assert_allclose(loose[[0, 18]], 0.5 * 4 * n, rtol=1e-6)
    np.testing.assert_allclose(loose[27:], TEXTURE * n, rtol=1e-6)


def test_fhog_vertical_step_edge():
    image = np.zeros((40, 40), np.float32)
    image[:, 20:] = 1.0  # dark to bright, left to right: gx > 0, theta = 0
    out = fhog(image)
    sensitive, insensitive = out[:18], out[18:27]
    energy_per_bin = sensitive.sum(axis=(1, 2))
    assert energy_per_bin.argmax() == 0
    assert energy_per_bin[0] > 0.5
    assert np.allclose(sensitive[1:], 0)  # every gradient is exactly horizontal
    assert insensitive.sum(axis=(1, 2)).argmax() == 0
    assert np.allclose(insensitive[[3, 4, 5]], 0)  # orthogonal orientations (near 90 degrees)
    # The energy sits on the cells around column 20, i.e. cell columns 4 and 5.
    column_profile = sensitive[0].sum(axis=0)
    assert set(np.argsort(column_profile)[-2:]) == {4, 5}
    assert np.allclose(column_profile[:3], 0) and np.allclose(column_profile[7:], 0)


def test_fhog_step_edge_polarity_uses_opposite_sensitive_bin():
    image = np.zeros((40, 40), np.float32)
    image[:, :20] = 1.0  # bright to dark: gx < 0, theta = pi, bin 9
    out = fhog(image)
    assert out[:18].sum(axis=(1, 2)).argmax() == 9
    assert out[18:27].sum(axis=(1, 2)).argmax() == 0  # the same insensitive orientation


def test_fhog_horizontal_edge_bins_follow_the_c_code():
    # A purely vertical gradient lies exactly on a bin boundary; the C float32 arithmetic gives bin 5 for
    # gy > 0 and bin 13 (not 14) for gy < 0 (ALGORITHM.md 4.1), i.e. insensitive bins 5 and 4.
    down = np.zeros((40, 40), np.float32)
    down[20:] = 1.0  # gy > 0
    up = down[::-1].copy()  # gy < 0
    assert fhog(down)[:18].sum(axis=(1, 2)).argmax() == 5
    assert fhog(up)[:18].sum(axis=(1, 2)).argmax() == 13
    assert np.allclose(fhog(up)[[14, 4, 5]], 0)


def test_fhog_invariant_to_colour_channel_order():
    image = random_image((48, 36, 3), seed=5)
    np.testing.assert_array_equal(fhog(image), fhog(image[:, :, ::-1]))
    np.testing.assert_array_equal(fhog(image), fhog(image[:, :, [1, 2, 0]]))


def test_fhog_gray_equals_replicated_gray():
    gray = random_image((33, 29), seed=6)
    np.testing.assert_array_equal(fhog(gray), fhog(np.dstack([gray] * 3)))
    np.testing.assert_array_equal(fhog(gray), fhog(gray[:, :, None]))


def test_fhog_picks_strongest_channel():
    strong = random_image((32, 32), seed=8)
    weak = 0.01 * random_image((32, 32), seed=9)
    np.testing.assert_array_equal(fhog(np.dstack([weak, strong, weak])), fhog(strong))


def test_fhog_input_scale_changes_only_the_epsilon():
    image = random_image((40, 40, 3), seed=2)
    np.testing.assert_allclose(fhog(image), fhog(image * 255), atol=2e-3)


def test_fhog_accepts_uint8_and_float64():
    image = (random_image((24, 24, 3)) * 255).astype(np.uint8)
    np.testing.assert_array_equal(fhog(image), fhog(image.astype(np.float64)))


@pytest.mark.parametrize("shape", [(40, 36, 3), (25, 30)])
def test_fhog_divisor_equals_dividing_a_float32_copy_first(shape):
    image = (random_image(shape, seed=4) * 255).astype(np.uint8)
    np.testing.assert_array_equal(fhog(image, divisor=255.0), fhog(image.astype(np.float32) / 255.0))
    batch = np.stack([image, image[::-1]])
    np.testing.assert_array_equal(fhog_batch(batch, divisor=255.0), fhog_batch(batch.astype(np.float32) / 255.0))


# --------------------------------------------------------------------------------------------------------
# fHOG of a batch of same-sized images
# --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [
    (30, 17, 3), (17, 30), (12, 16, 1), (21, 22, 2),  # colour, gray, one and two channels
    (4, 40), (7, 40, 3), (40, 5), (6, 7, 3), (4, 4),  # thin grids one cell high or wide, and a single cell
])
@pytest.mark.parametrize("n_images", [1, 3, 31])
def test_fhog_batch_equals_one_call_per_image(shape, n_images):
    images = 255 * random_image((n_images, *shape), seed=n_images)
    batch = fhog_batch(images)
    assert batch.shape == (n_images, 31, shape[0] // 4, shape[1] // 4)
    assert batch.dtype == np.float32 and batch.flags.c_contiguous
    for image, features in zip(images, batch):
        np.testing.assert_array_equal(features, fhog(image))


def test_fhog_batch_does_not_mix_images_at_their_borders():
    # Neighbours with very different content: any gradient or cell bleeding across them would show.
    rng = np.random.default_rng(12)
    images = np.stack([np.zeros((13, 10, 3)), np.full((13, 10, 3), 255.0), rng.integers(0, 3, (13, 10, 3)),
                       np.tile(np.arange(10.0), (13, 1))[:, :, None].repeat(3, axis=2)]).astype(np.float32)
    batch = fhog_batch(images)
    assert not batch[0].any() and not batch[1].any()  # flat images stay exactly zero
    for image, features in zip(images, batch):
        np.testing.assert_array_equal(features, fhog(image))


def test_fhog_batch_other_cell_size_clip_and_input_types():
    images = (255 * random_image((5, 14, 19, 3), seed=13)).astype(np.uint8)
    batch = fhog_batch(images, cell_size=3, clip=0.3)
    for image, features in zip(images, batch):
        np.testing.assert_array_equal(features, fhog(image, cell_size=3, clip=0.3))
        np.testing.assert_allclose(features, reference_fhog(image.astype(np.float32), cell=3, clip=0.3),
                                   rtol=1e-5, atol=1e-6)


def test_fhog_batch_rejects_too_small_and_bad_rank():
    with pytest.raises(ValueError):
        fhog_batch(random_image((2, 3, 40)))
    with pytest.raises(ValueError):
        fhog_batch(random_image((8, 8)))
    with pytest.raises(ValueError):
        fhog_batch(random_image((2, 8, 8, 3, 1)))


# --------------------------------------------------------------------------------------------------------
# Color Names
# --------------------------------------------------------------------------------------------------------

def solid_bgr(b, g, r, shape=(16, 16)):
    patch = np.zeros(shape + (3,), np.uint8)
    patch[:] = (b, g, r)
    return patch


@pytest.mark.parametrize("shape", [(16, 16, 3), (23, 17, 3), (230, 174, 3), (5, 9, 3)])
def test_color_names_shape_dtype_layout(shape):
    patch = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    out = color_names(patch)
    assert out.shape == (11, shape[0] // 4, shape[1] // 4)
    assert out.dtype == np.float32
    assert out.flags.c_contiguous


def test_color_names_cells_sum_to_one():
    patch = np.random.default_rng(1).integers(0, 256, (40, 28, 3), dtype=np.uint8)
    out = color_names(patch)
    np.testing.assert_allclose(out.sum(axis=0), 1.0, atol=1e-5)
    assert out.min() >= 0


@pytest.mark.parametrize("bgr, channel", [
    ((0, 0, 255), CN_RED), ((0, 0, 0), CN_BLACK), ((255, 255, 255), CN_WHITE),
    ((255, 0, 0), CN_BLUE), ((0, 255, 0), CN_GREEN),
])
def test_color_names_pure_colours(bgr, channel):
    out = color_names(solid_bgr(*bgr))
    assert (out.argmax(axis=0) == channel).all()
    assert out[channel].min() > 0.25  # the table is soft: black (0, 0, 0) has p = 0.29


def test_color_names_reads_bgr_order():
    red_bgr = solid_bgr(0, 0, 255)
    blue_bgr = red_bgr[:, :, ::-1].copy()
    assert (color_names(red_bgr).argmax(axis=0) == CN_RED).all()
    assert (color_names(blue_bgr).argmax(axis=0) == CN_BLUE).all()


def test_color_names_matches_table_lookup_of_cell_means():
    # Uniform 4x4 cells: INTER_AREA returns each cell's colour exactly, so the output is a plain lookup.
    rng = np.random.default_rng(2)
    cells = rng.integers(0, 256, (3, 5, 3), dtype=np.uint8)
    patch = np.repeat(np.repeat(cells, 4, axis=0), 4, axis=1)
    table = _package_table()
    b, g, r = (cells[:, :, i].astype(int) for i in range(3))
    expected = table[r // 8 + 32 * (g // 8) + 1024 * (b // 8)].transpose(2, 0, 1)
    np.testing.assert_array_equal(color_names(patch), expected)


def test_color_names_averages_each_cell_before_lookup():
    patch = np.zeros((8, 8, 3), np.uint8)
    patch[:, :, 2] = np.where(np.arange(8) % 2 == 0, 200, 0)[None, :]  # red stripes, 1 px wide
    table = _package_table()
    expected = table[100 // 8]  # mean colour R = 100, G = B = 0
    np.testing.assert_allclose(color_names(patch)[:, 0, 0], expected)


def test_color_names_grayscale_fallback():
    gray = np.random.default_rng(3).integers(0, 256, (20, 24), dtype=np.uint8)
    expected = color_names(np.dstack([gray] * 3))
    np.testing.assert_array_equal(color_names(gray), expected)
    np.testing.assert_array_equal(color_names(gray[:, :, None]), expected)


def test_color_names_rejects_float_input():
    with pytest.raises(TypeError):
        color_names(np.zeros((8, 8, 3), np.float32))


def _package_table() -> np.ndarray:
    from importlib import resources
    with resources.files("tacf.data").joinpath("w2c.npz").open("rb") as handle:
        return np.load(handle)["w2c"]


def test_compiled_loops_need_no_writable_cache_folder():
    """numba's cache=True raises at import where it cannot write its cache (a read-only container: `import
    tacf.tracker` failed with "no locator available"); tacf.compiled then compiles in the process. A function
    whose source is in no file has no cache folder either."""
    import numba

    from tacf.compiled import compiled

    namespace = {}
    exec("def add_one(x):\n    return x + 1\n", namespace)
    with pytest.raises(RuntimeError, match="no locator available"):
        numba.njit(cache=True)(namespace["add_one"])
    assert compiled(namespace["add_one"])(41) == 42
