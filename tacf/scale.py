"""DSST 1-D scale filter (ALGORITHM.md section 11; patches per section 3.4; pipeline steps 12 and 14f of section 7).

The filter is a single-channel correlation filter along the scale axis: one feature vector per candidate scale,
stacked into a matrix, Fourier-transformed over the scale axis only. Detection picks the scale whose response is
the first maximum and multiplies the current scale factor by it; training keeps a running numerator and
denominator (EMA with `scale_learning_rate`, set at the first call). Neither runs while less than
`scale_min_visible` of the box lies in the frame (`ScaleFilter.sees_enough`).

Layout: MATLAB keeps Xs as (D, num_scales); here it is stored transposed, (num_scales, D), so each scale's
feature vector is contiguous, and the FFT runs over axis 0. Each vector is flattened in MATLAB's column-major
order (row fastest, then column, then channel) for parity; the filter itself does not depend on that order.
The feature vectors are real, so a real FFT (`rfft`/`irfft` with n = num_scales) gives the same response as the
full complex FFT at half the cost. Samples, spectra and the model are float32 (complex64), as the translation
filters are: float64 picked the same scale in every frame of the ten UAV sequences (boxes identical) at ~5 % more
time per frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.fft
from scipy.signal.windows import hann

from tacf.boxes import visible_fraction
from tacf.config import TrackerConfig
from tacf.features import fhog_batch
from tacf.fft import squared_magnitude
from tacf.geometry import sample_patch

FeatureFn = Callable[[np.ndarray, int], np.ndarray]
"""features(patch uint8 HxW or HxWxC (raw 0-255 values), cell_size) -> (C, H // cell, W // cell)."""
BatchFeatureFn = Callable[[np.ndarray, int], np.ndarray]
"""The same for N patches of one size at once: (N, H, W[, C]) -> (N, C, H // cell, W // cell)."""

SCALE_FEATURE_CHANNELS = 31  # fHOG channels kept (section 11, step 2)


def scale_label(num_scales: int, sigma_factor: float) -> np.ndarray:
    """Centred (not wrapped) Gaussian over the scale index, sigma = sqrt(num_scales) * sigma_factor (section 11)."""
    offsets = np.arange(num_scales) - (num_scales - 1) / 2
    sigma = np.sqrt(num_scales) * sigma_factor
    return np.exp(-0.5 * offsets**2 / sigma**2)


def scale_window(num_scales: int) -> np.ndarray:
    """MATLAB's symmetric hann(num_scales): end points are 0 (section 11, section 2 "Windows")."""
    return hann(num_scales, sym=True)


def scale_factors(num_scales: int, scale_step: float) -> np.ndarray:
    """scale_step ** (centre - i): index 0 is the largest scale, the centre index is 1 (section 11)."""
    centre = (num_scales - 1) // 2
    return scale_step ** (centre - np.arange(num_scales, dtype=np.float64))


def scale_model_size(norm_target_sz, max_area: float, cell_size: int) -> np.ndarray:
    """floor(norm_target_sz * scale_model_factor), the factor shrinking the area to at most max_area (section 11).

    The result is kept at least one cell per side: a thinner model would give an empty feature vector, a case the
    MATLAB code leaves undefined; it never triggers for areas produced by section 2.
    """
    norm_target_sz = np.asarray(norm_target_sz, dtype=np.float64)
    area = float(np.prod(norm_target_sz))
    model_factor = 1.0 if area <= max_area else np.sqrt(max_area / area)
    return np.maximum(np.floor(norm_target_sz * model_factor), cell_size)


def scale_limits(scale_step: float, image_hw, base_target_sz, bg_area) -> tuple[float, float]:
    """(min_scale, max_scale): whole powers of scale_step; the background area keeps 5 px, the target fits
    (section 11). The first box's scale, 1, is always within them: for a background area under 5 px (a 1x1 box, a
    frame 6 px high) the code's minimum is above 1, and the box grew on the first update of identical frames."""
    log_step = np.log(scale_step)
    smallest = np.log(np.max(5.0 / np.asarray(bg_area, dtype=np.float64))) / log_step
    largest = np.log(np.min(np.asarray(image_hw, dtype=np.float64) / np.asarray(base_target_sz))) / log_step
    return min(float(scale_step ** np.ceil(smallest)), 1.0), max(float(scale_step ** np.floor(largest)), 1.0)


def scale_patch_rects(pos, base_target_sz, scale_factor: float, factors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Top-left corners and sizes, both (num_scales, 2) int, of the scale patches (section 3.4, 0-based).

    size = max(floor(base_target_sz * scale_factor * factor), 2); MATLAB's 1-based rows are
    floor(pos) + (1..h) - floor(h / 2), so the 0-based first row is floor(pos) + 1 - floor(h / 2).
    """
    sizes = np.maximum(np.floor(np.outer(factors * scale_factor, base_target_sz)), 2)
    top_left = np.floor(np.asarray(pos, dtype=np.float64)) + 1 - np.floor(sizes / 2)
    return top_left.astype(np.int64), sizes.astype(np.int64)


def filter_terms(label_hat: np.ndarray, sample_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One sample's numerator Ys conj(Xs), per feature, and denominator sum_d |Xs|^2 (section 11, training)."""
    num = label_hat[:, None] * np.conj(sample_hat)
    den = np.sum(squared_magnitude(sample_hat), axis=1)
    return num, den


def scale_response(num: np.ndarray, den: np.ndarray, sample_hat: np.ndarray, reg: float,
                   num_scales: int) -> np.ndarray:
    """real(ifft(sum_d(num Xs) / (den + lambda))) over the scale axis, from half spectra (section 11, detection)."""
    return scipy.fft.irfft(np.sum(num * sample_hat, axis=1) / (den + reg), n=num_scales)


@dataclass(frozen=True)
class _RecentSample:
    """A scale sample of one image: its patch rectangles, their feature vectors, the sample's spectrum."""

    image: np.ndarray
    rects: list
    vectors: dict
    spectrum: np.ndarray


class ScaleFilter:
    """The DSST scale filter of one sequence (section 11).

    `cfg` is a TrackerConfig, or any config with its cell_size, fast_resize and scale fields (tacf.staple's
    StapleConfig). `features` is the per-patch feature function; it exists so tests can inject a cheap stand-in
    (see FeatureFn).
    By default all scale patches of a sample go through the project's fHOG in one batch call (`fhog_batch`),
    which gives the same values as one `fhog` call per patch at a fraction of the per-call overhead.
    """

    def __init__(self, cfg: TrackerConfig, image_hw, base_target_sz, norm_target_sz, bg_area,
                 features: FeatureFn | None = None) -> None:
        self._cell_size = cfg.cell_size
        self._learning_rate = cfg.scale_learning_rate
        self._lambda = cfg.scale_lambda
        self._num_scales = cfg.num_scales
        self._fast_resize = cfg.fast_resize
        self._min_visible = cfg.scale_min_visible
        self._base_target_sz = np.asarray(base_target_sz, dtype=np.float64)
        self._batch_features = fhog_batch if features is None else _one_by_one(features)

        self._factors = scale_factors(cfg.num_scales, cfg.scale_step)
        self._window = scale_window(cfg.num_scales).astype(np.float32)
        self._sampled = np.flatnonzero(self._window)  # zero-weight scales contribute zero features: skip them
        self._label_hat = scipy.fft.rfft(scale_label(cfg.num_scales, cfg.scale_sigma_factor)).astype(np.complex64)
        self._model_sz = scale_model_size(norm_target_sz, cfg.scale_model_max_area, cfg.cell_size)
        self._min_scale, self._max_scale = scale_limits(cfg.scale_step, image_hw, base_target_sz, bg_area)
        self._num: np.ndarray | None = None  # (num_scales // 2 + 1, D) complex
        self._den: np.ndarray | None = None  # (num_scales // 2 + 1,) real
        # What estimate() computed, for the update_model() that follows on the same image: the feature vectors by
        # patch rectangle (at the same position most of the patches recur) and the spectrum of the whole sample
        # (all of them recur when the scale did not change, as in most frames).
        self._recent: _RecentSample | None = None

    @property
    def min_scale(self) -> float:
        return self._min_scale

    @property
    def max_scale(self) -> float:
        return self._max_scale

    @property
    def model_size(self) -> np.ndarray:
        """scale_model_sz (height, width): every scale patch is resized to this."""
        return self._model_sz.copy()

    def update_model(self, image: np.ndarray, pos, scale_factor: float) -> None:
        """Train at (pos, scale_factor): the first call sets num/den, later calls blend them in (section 11), those
        on a box mostly beyond the frame excepted (sees_enough).

        What the last estimate() on this same image computed is reused: all of it when the rectangles are the same
        (the scale did not change), else the feature vectors of the patches that recur.
        """
        if self._num is not None and not self.sees_enough(image, pos, scale_factor):
            self._recent = None
            return
        num, den = filter_terms(self._label_hat, self._sample_hat(image, pos, scale_factor))
        self._recent = None  # the next image is another
        if self._num is None:
            self._num, self._den = num, den
            return
        rate = self._learning_rate
        self._num = (1 - rate) * self._num + rate * num
        self._den = (1 - rate) * self._den + rate * den

    def estimate(self, image: np.ndarray, pos, scale_factor: float) -> float:
        """The new scale factor: scale_factor times the best relative scale, clamped (section 11, detection); the
        same one, clamped, while the box lies mostly beyond the frame (sees_enough)."""
        if self._num is None:
            raise RuntimeError("ScaleFilter.estimate() called before update_model()")
        self._recent = None
        if not self.sees_enough(image, pos, scale_factor):
            return float(np.clip(scale_factor, self._min_scale, self._max_scale))
        sample_hat = self._sample_hat(image, pos, scale_factor)
        response = scale_response(self._num, self._den, sample_hat, self._lambda, self._num_scales)
        if not np.all(np.isfinite(response)) or response.max() <= response.min():
            # A sample without a gradient (a blank frame, a uniform occluder) answers 0 at every scale, and the
            # first maximum would be the largest scale: 1.6 times the box on each such frame, for good.
            return scale_factor
        best = int(np.argmax(response))  # first maximum, like MATLAB's find(... == max)
        new_factor = scale_factor * self._factors[best]
        return float(np.clip(new_factor, self._min_scale, self._max_scale))

    def sees_enough(self, image: np.ndarray, pos, scale_factor: float) -> bool:
        """Whether at least scale_min_visible of the box at scale_factor lies in the image. Beyond the image the
        scale patches are its border pixels repeated: beyond a corner one flat colour, which has no fHOG features,
        so the smaller scales, more of which lies there, answer less and the first maximum moves to larger ones:
        a target leaving through a corner grew the box up to 5.9 times in 20 frames (tests/test_tracker.py)."""
        box_hw = self._base_target_sz * scale_factor
        return visible_fraction(pos, box_hw, image.shape) >= self._min_visible

    def _sample_hat(self, image: np.ndarray, pos, scale_factor: float) -> np.ndarray:
        """FFT over the scale axis of the windowed scale sample, (num_scales // 2 + 1, D)."""
        rects = self._rects(pos, scale_factor)
        recent = self._recent if self._recent is not None and self._recent.image is image else None
        if recent is not None and recent.rects == rects:
            return recent.spectrum
        vectors = self._feature_vectors(image, rects, recent.vectors if recent is not None else {})
        spectrum = scipy.fft.rfft(self._windowed(vectors, rects), axis=0)
        self._recent = _RecentSample(image, rects, vectors, spectrum)
        return spectrum

    def sample(self, image: np.ndarray, pos, scale_factor: float) -> np.ndarray:
        """Xs transposed, computed afresh (for inspection; the filter uses its spectrum, with what it can reuse):
        row i is the flattened feature vector of scale i times scale_window[i] (section 11)."""
        rects = self._rects(pos, scale_factor)
        return self._windowed(self._feature_vectors(image, rects, {}), rects)

    def _rects(self, pos, scale_factor: float) -> list[tuple[int, int, int, int]]:
        """(top, left, height, width) of each sampled scale's patch, as plain ints: cheap to hash and slice with."""
        top_left, sizes = (a.tolist() for a in scale_patch_rects(pos, self._base_target_sz, scale_factor,
                                                                  self._factors))
        return [(*top_left[i], *sizes[i]) for i in self._sampled]

    def _feature_vectors(self, image: np.ndarray, rects: list, known: dict) -> dict[tuple, np.ndarray]:
        """The feature vector of every rectangle, by rectangle: those in `known` as they are, the others new."""
        missing = [rect for rect in rects if rect not in known]
        if not missing:
            return known
        patches = np.stack([sample_patch(image, rect[:2], rect[2:], self._model_sz, self._fast_resize)
                            for rect in missing])
        return {**known, **dict(zip(missing, self._patch_features(patches)))}

    def _windowed(self, vectors: dict[tuple, np.ndarray], rects: list) -> np.ndarray:
        """The sample matrix: the vectors of the sampled scales, windowed, and zero rows for the others."""
        stacked = np.stack([vectors[rect] for rect in rects])
        sample = np.zeros((self._num_scales, stacked.shape[1]), dtype=np.float32)
        sample[self._sampled] = stacked * self._window[self._sampled, None]
        return sample

    def _patch_features(self, patches: np.ndarray) -> np.ndarray:
        """fHOG of patches already resized to scale_model_sz, (N, H, W[, C]) raw 0-255 values, one batch call;
        row n is patch n's feature map flattened column-major (section 11)."""
        feature_maps = self._batch_features(patches, self._cell_size)
        feature_maps = feature_maps[:, :SCALE_FEATURE_CHANNELS].transpose(0, 1, 3, 2)
        return feature_maps.reshape(len(patches), -1)  # (C, W, H) C-order == (H, W, C) column-major


def _one_by_one(features: FeatureFn) -> BatchFeatureFn:
    """A batch feature function that calls the per-patch `features` on each patch in turn."""
    return lambda patches, cell_size: np.stack([features(patch, cell_size) for patch in patches])
