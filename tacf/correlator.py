"""Per-channel kernel cross-correlators (KCC form), batched over the channel axis (ALGORITHM.md section 5).

One feature type (fHOG or Color Names) gets one independent single-channel filter per channel:

    W_d = K_d . Y / (K_d . conj(K_d) + lambda1 + context_d)        with K_d = F(k(x_d, x_d))

All arrays are (C, H, W) in space and (C, H, W//2+1) in frequency: the signals are real, so real FFTs over
the last two axes serve every channel in one call. The zero displacement sits at the array's corner.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tacf.fft import irfft2, rfft2, squared_magnitude

# exp(-u) = 1 - u + r with 0 <= r <= u^2 / 2 for u >= 0: under this exponent the first-order kernel is within
# 1e-5 of the exact one, element by element (float32 resolves about 6e-8 around 1).
FIRST_ORDER_EXPONENT = 4.5e-3
# TrackerConfig.fast_kernel: the first-order kernel wherever u stays under this, within u^2 / 2 <= 0.045 of the exact
# one. On the 15 sequences of ../shared/data the bound on u reaches 0.27 at most and u itself 0.11 (docs/decisions.md).
FAST_KERNEL_EXPONENT = 0.3
# The Gaussian kernel's exponent -u is never positive (Cauchy-Schwarz), but float32 computes it as a difference of
# large terms. On real frames it comes out at most 1.3e-7 above 0 (fast_kernel off, the first 60 frames of the 15
# sequences); for a context patch scaled up a million times (context_lambda2 and context_penalty_total at their
# ceilings) at up to 2,560: exp overflowed, and the inf context energy zeroed HOG channels' filters. The cap is far
# above rounding on real frames, whose kernels keep every bit (the boxes are the same).
MAX_GAUSSIAN_EXPONENT = 1e-3


def gaussian_label(grid_hw: tuple[int, int], sigma: float) -> np.ndarray:
    """Desired output: a Gaussian whose peak sits at (H-1, W-1), i.e. displacement (-1, -1).

    The one-cell shift mirrors the authors' label and is undone by the response crop (response.crop_centre).
    """
    height, width = grid_hw
    rows = np.arange(-((height - 1) // 2), (height - 1) // 2 + 1)
    cols = np.arange(-((width - 1) // 2), (width - 1) // 2 + 1)
    label = np.zeros(grid_hw)
    values = np.exp(-(rows[:, None] ** 2 + cols[None, :] ** 2) / (2 * sigma**2))
    label[np.ix_((rows - 1) % height, (cols - 1) % width)] = values
    return label


@dataclass(frozen=True)
class GaussianKernel:
    """k(a, b)[t] = exp(-(|a|^2 + |b|^2 - 2 (a * b)[t]) / (sigma^2 N)), per channel."""

    sigma: float
    first_order_exponent: float = FIRST_ORDER_EXPONENT

    def __call__(self, cross: np.ndarray, sq_norm_a: np.ndarray, sq_norm_b: np.ndarray) -> np.ndarray:
        """The kernel map, computed in place in `cross` (the caller's fresh inverse FFT)."""
        inverse_width = 1.0 / (self.sigma**2 * cross.shape[-1] * cross.shape[-2])
        # exp((2 cross - |a|^2 - |b|^2) / (sigma^2 N)), in place: two passes over the maps, then the exp.
        cross *= 2 * inverse_width
        cross -= (sq_norm_a + sq_norm_b) * inverse_width
        # OpenCV's float32 exp is ~6x faster than numpy's here and as close to the float64 exp (both within
        # 2e-7); the boxes on the UAV sequences are identical with either (docs/speed.md).
        rows = cross.reshape(-1, cross.shape[-1])  # OpenCV takes 2-D arrays
        np.minimum(rows, MAX_GAUSSIAN_EXPONENT, out=rows)
        cv2.exp(rows, rows)
        return rows.reshape(cross.shape)

    def first_order_kernel_hat(self, cross_hat: np.ndarray, sq_norm_a: np.ndarray, sq_norm_b: np.ndarray,
                               n: int) -> np.ndarray | None:
        """F(k(a, b)) in closed form when the kernel stays close to 1, else None (compute it exactly).

        k(a, b)[t] = exp(-u[t]) with u = (|a|^2 + |b|^2 - 2 c[t]) / (sigma^2 N), c the circular cross-correlation,
        so 0 <= u <= (|a| + |b|)^2 / (sigma^2 N) (Cauchy-Schwarz). Under `first_order_exponent`, k = 1 - u to
        within u^2 / 2, whose transform needs no FFT:
        F(1 - u) = N delta (1 - (|a|^2 + |b|^2) / (sigma^2 N)) + 2 F(c) / (sigma^2 N).
        cross_hat: F(c) (..., H, W//2+1); sq_norm_a, sq_norm_b: |a|^2, |b|^2 broadcastable against it; n: H * W.
        """
        inverse_width = 1.0 / (self.sigma**2 * n)
        bound = (np.sqrt(sq_norm_a) + np.sqrt(sq_norm_b)) ** 2 * inverse_width
        if float(np.max(bound)) > self.first_order_exponent:
            return None
        kernel_hat = (2.0 * inverse_width) * cross_hat
        kernel_hat[..., 0, 0] += n * (1.0 - (sq_norm_a + sq_norm_b)[..., 0, 0] * inverse_width)
        return kernel_hat


@dataclass(frozen=True)
class PolynomialKernel:
    """k(a, b)[t] = ((a * b)[t] / N + offset) ** degree, per channel."""

    offset: float
    degree: float

    def __call__(self, cross: np.ndarray, sq_norm_a: np.ndarray, sq_norm_b: np.ndarray) -> np.ndarray:
        n = cross.shape[-1] * cross.shape[-2]
        return (cross / n + self.offset) ** self.degree

    def first_order_kernel_hat(self, cross_hat: np.ndarray, sq_norm_a: np.ndarray, sq_norm_b: np.ndarray,
                               n: int) -> None:
        """No closed form is used for this kernel (see GaussianKernel)."""
        return None


def _inverse_dft_weights(grid_hw: tuple[int, int], point: tuple[int, int]) -> np.ndarray:
    """v (H, W//2+1) such that irfft2(s, grid_hw)[point] == real(sum(s * v)) for every half spectrum s.

    The columns 0 and W/2 (W even) stand for themselves, the others also for their mirror images: weight 2.
    """
    height, width = grid_hw
    rows = np.arange(height)[:, None]
    cols = np.arange(width // 2 + 1)[None, :]
    multiplicity = np.where((cols == 0) | (2 * cols == width), 1.0, 2.0)
    phase = np.exp(2j * np.pi * (rows * point[0] / height + cols * point[1] / width))
    return multiplicity * phase / (height * width)


def _sq_norms(x: np.ndarray) -> np.ndarray:
    """Squared norm of every (H, W) slice, shaped to broadcast against the slices."""
    return np.einsum("...hw,...hw->...", x, x)[..., None, None]


class CorrelatorBank:
    """The filters of one feature type: training with an optional context term, EMA model, detection."""

    def __init__(self, kernel, label: np.ndarray, lambda1: float, learning_rate: float):
        self.kernel = kernel
        self.grid_hw = label.shape
        self.label_hat = rfft2(label.astype(np.float32))
        # For fresh_self_response_maxima_and_means: the label's peak, and whether its spectrum, centred there, is
        # non-negative (true of any label narrow enough for its grid, as TACF's are).
        label_peak = np.unravel_index(np.argmax(label), label.shape)
        centred_label_hat = rfft2(np.roll(label, [-i for i in label_peak], axis=(0, 1))).real
        self._self_responses_peak_at_label = bool(centred_label_hat.min() >= -1e-9 * centred_label_hat.max())
        self._at_label_peak = _inverse_dft_weights(self.grid_hw, label_peak).astype(np.complex64)
        self.lambda1 = lambda1
        self.learning_rate = learning_rate
        self.model_x: np.ndarray | None = None  # template in space (kept for its norms)
        self.model_x_hat: np.ndarray | None = None
        self.model_filter_hat: np.ndarray | None = None
        self._fresh: tuple[np.ndarray, np.ndarray] | None = None

    # -- kernels ------------------------------------------------------------------------------------------
    def spectrum(self, x: np.ndarray) -> np.ndarray:
        """rfft2 of every (H, W) slice of x: compute it once where several steps need it."""
        return rfft2(x)

    def _ifft(self, x_hat: np.ndarray) -> np.ndarray:
        return irfft2(x_hat, self.grid_hw)

    def auto_kernel_hat(self, x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
        """F(k(x_d, x_d)) for every channel d (the leading axes are batch axes)."""
        norms = _sq_norms(x)
        return self._kernel_hat(x_hat * x_hat.conj(), norms, norms)

    def cross_kernel_hat(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """F(k(z_d, model_x_d)): a target displaced by +d in z peaks at +d."""
        return self._kernel_hat(z_hat * self.model_x_hat.conj(), _sq_norms(z), _sq_norms(self.model_x))

    def _kernel_hat(self, cross_hat: np.ndarray, sq_norm_a: np.ndarray, sq_norm_b: np.ndarray) -> np.ndarray:
        """F(k) from the cross-correlation's spectrum: in closed form where the kernel allows it, else through
        the kernel map in space."""
        n = self.grid_hw[0] * self.grid_hw[1]
        kernel_hat = self.kernel.first_order_kernel_hat(cross_hat, sq_norm_a, sq_norm_b, n)
        if kernel_hat is None:
            kernel_hat = self.spectrum(self.kernel(self._ifft(cross_hat), sq_norm_a, sq_norm_b))
        return kernel_hat

    def context_energy(self, context_x: np.ndarray, context_x_hat: np.ndarray | None = None,
                       scales: np.ndarray | None = None) -> np.ndarray:
        """sum_s |F(k(p_s x_s, p_s x_s))|^2 over context patches x_s (S, C, H, W), each scaled by p_s = scales[s]
        (default 1) before the kernel; context_x_hat = spectrum(context_x) if already known (it is shared with
        the penalty responses).

        The scales are about sqrt(lambda2) = 1/16, so the Gaussian auto-kernel of a scaled patch stays within
        ~2e-3 of 1 (measured on the UAV sequences) and its first-order closed form serves, without the two FFTs
        per channel and patch of the exact kernel; larger scales take the exact path.
        """
        if context_x_hat is None:
            context_x_hat = self.spectrum(context_x)
        scales = np.ones(1, np.float32) if scales is None else np.asarray(scales, np.float32)
        scales = scales.reshape(-1, 1, 1, 1)
        squares = scales**2
        sq_norms = _sq_norms(context_x) * squares  # |p_s x_s|^2 = p_s^2 |x_s|^2
        power = squared_magnitude(context_x_hat) * squares
        kernel_hat = self._kernel_hat(power, sq_norms, sq_norms)
        return np.sum(squared_magnitude(kernel_hat), axis=0)

    # -- training ------------------------------------------------------------------------------------------
    def train(self, x: np.ndarray, context_energy: np.ndarray | None = None) -> None:
        """Learn fresh filters on x (C, H, W) and blend them into the model."""
        x_hat = self.spectrum(x)
        kernel_hat = self.auto_kernel_hat(x, x_hat)
        denominator = squared_magnitude(kernel_hat) + self.lambda1
        if context_energy is not None:
            denominator = denominator + context_energy
        filter_hat = kernel_hat * self.label_hat
        filter_hat *= 1.0 / denominator  # a real reciprocal: half the time of a complex division
        if self.model_x is None:  # copies: the model is updated in place
            self.model_x, self.model_x_hat, self.model_filter_hat = x.copy(), x_hat.copy(), filter_hat.copy()
        else:
            rate = self.learning_rate
            for model, fresh in ((self.model_x, x), (self.model_x_hat, x_hat), (self.model_filter_hat, filter_hat)):
                model *= 1 - rate  # (1 - rate) model + rate fresh, in place
                model += rate * fresh
        self._fresh = filter_hat, kernel_hat

    def fresh_self_response_maxima_and_means(self) -> tuple[np.ndarray, np.ndarray]:
        """Max and mean of each channel's R_d = real(F^-1(W_d . K_d)) for the filters just trained: how well
        each channel answers its own sample. They feed dimensional attention (ALGORITHM.md section 8).

        No inverse FFT is needed. W_d K_d = K_d^2 Y / (|K_d|^2 + lambda1 + context): the auto-kernel is even, so
        K_d is real, and the label's spectrum Y is non-negative once centred on its peak. A map whose spectrum is
        real and non-negative peaks at its origin, so R_d peaks where the label does (on all 54,264 self-responses
        of the ten UAV sequences, measured): its maximum is that one inverse-DFT value, its mean the DC term / N.
        """
        filter_hat, kernel_hat = self._fresh
        self_response_hat = filter_hat * kernel_hat
        if not self._self_responses_peak_at_label:  # a label too wide for its grid: search the whole maps
            responses = self._ifft(self_response_hat)
            return responses.max(axis=(-2, -1)), responses.mean(axis=(-2, -1))
        maxima = np.einsum("chw,hw->c", self_response_hat, self._at_label_peak).real
        means = self_response_hat[:, 0, 0].real / (self.grid_hw[0] * self.grid_hw[1])
        return maxima, means

    # -- detection -----------------------------------------------------------------------------------------
    def channel_response_hats(self, z: np.ndarray, z_hat: np.ndarray | None = None) -> np.ndarray:
        """F(R_d) for every channel of the sample z (..., C, H, W); z_hat = spectrum(z) if already known."""
        return self.model_filter_hat * self.cross_kernel_hat(z, self.spectrum(z) if z_hat is None else z_hat)

    def response(self, z: np.ndarray, channel_weights: np.ndarray | None = None,
                 z_hat: np.ndarray | None = None) -> np.ndarray:
        """sum_d w_d R_d as one H x W map per sample z (..., C, H, W): the weighted channel sum is taken before
        the inverse FFT."""
        hats = self.channel_response_hats(z, z_hat)
        if channel_weights is None:
            summed = hats.sum(axis=-3)
        else:
            summed = (channel_weights.astype(hats.real.dtype)[:, None, None] * hats).sum(axis=-3)
        return self._ifft(summed)

    def pooled_kernel_response(self, z: np.ndarray, channel_weights: np.ndarray | None = None,
                               z_hat: np.ndarray | None = None) -> np.ndarray:
        """response() with one kernel for all channels instead of one per channel: k(z, model_x) of the channel
        means of the cross-correlations and squared norms (KCF's multi-channel kernel; for the Gaussian, the
        geometric mean of the per-channel kernels), under the channel-weighted sum of the filters,
        sum_d w_d W_d. The context challenge factors use it: with the exact kernel three FFTs per sample instead of
        2 C + 1; where the first-order form serves (TrackerConfig.fast_kernel), one inverse FFT either way."""
        z_hat = self.spectrum(z) if z_hat is None else z_hat
        kernel_hat = self._kernel_hat((z_hat * self.model_x_hat.conj()).mean(axis=-3), _sq_norms(z).mean(axis=-3),
                                      _sq_norms(self.model_x).mean(axis=-3))
        weights = np.ones(len(self.model_filter_hat)) if channel_weights is None else channel_weights
        weighted_filter = (weights.astype(np.float32)[:, None, None] * self.model_filter_hat).sum(axis=-3)
        return self._ifft(kernel_hat * weighted_filter)
