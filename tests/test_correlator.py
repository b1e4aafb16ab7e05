"""The kernel correlators: closed form against a direct least-squares solve, labels, shift recovery."""
import cv2
import numpy as np
import pytest
import scipy.fft as sfft

from tacf.attention import pme
from tacf.correlator import FAST_KERNEL_EXPONENT, CorrelatorBank, GaussianKernel, PolynomialKernel, gaussian_label
from tacf.features import fhog
from tacf.response import crop_centre, peak_offset


def _convolution_matrix(kernel: np.ndarray) -> np.ndarray:
    """A with A @ w.ravel() == real(ifft2(fft2(w) * fft2(kernel))).ravel(): circular convolution by kernel."""
    height, width = kernel.shape
    columns = []
    for index in range(height * width):
        impulse = np.zeros(kernel.shape)
        impulse.flat[index] = 1.0
        columns.append(np.real(np.fft.ifft2(np.fft.fft2(impulse) * np.fft.fft2(kernel))).ravel())
    return np.stack(columns, axis=1)


def _spatial_kernel(bank: CorrelatorBank, x: np.ndarray) -> np.ndarray:
    return sfft.irfft2(bank.auto_kernel_hat(x, sfft.rfft2(x)), s=x.shape[-2:])


@pytest.mark.parametrize("kernel", [GaussianKernel(0.5), PolynomialKernel(1.0, 2.0)])
def test_closed_form_minimises_the_objective(kernel):
    """w* = argmin |K0 w - y|^2 + lambda1 |w|^2 + sum_s |Ks w|^2, solved directly, equals the Fourier filter."""
    rng = np.random.default_rng(0)
    grid = (6, 5)
    lambda1 = 1e-2
    x = rng.normal(size=(1, *grid))
    contexts = 0.3 * rng.normal(size=(2, 1, *grid))
    label = gaussian_label(grid, sigma=0.8)
    bank = CorrelatorBank(kernel, label, lambda1, learning_rate=0.01)
    bank.train(x, bank.context_energy(contexts))
    fourier_solution = sfft.irfft2(bank.model_filter_hat[0], s=grid).ravel()

    a_object = _convolution_matrix(_spatial_kernel(bank, x)[0])
    normal = a_object.T @ a_object + lambda1 * np.eye(a_object.shape[1])
    for context in contexts:
        a_context = _convolution_matrix(_spatial_kernel(bank, context)[0])
        normal += a_context.T @ a_context
    direct = np.linalg.solve(normal, a_object.T @ label.astype(np.float32).ravel())
    np.testing.assert_allclose(fourier_solution, direct, rtol=2e-3, atol=2e-4)


def test_context_term_lowers_the_response_on_the_context_patch():
    rng = np.random.default_rng(1)
    grid = (20, 20)
    x = rng.random((1, *grid))
    distractor = rng.random((1, *grid))
    label = gaussian_label(grid, 1.0)
    plain = CorrelatorBank(GaussianKernel(0.5), label, 1e-4, 0.01)
    plain.train(x)
    with_context = CorrelatorBank(GaussianKernel(0.5), label, 1e-4, 0.01)
    with_context.train(x, with_context.context_energy(distractor[None]))
    assert with_context.response(distractor).max() < 0.5 * plain.response(distractor).max()
    assert with_context.response(x).max() > 0.3  # still answers the target


def test_label_peak_sits_at_minus_one_displacement():
    label = gaussian_label((57, 43), 1.5)
    assert np.unravel_index(np.argmax(label), label.shape) == (56, 42)
    assert label.max() == pytest.approx(1.0)
    even = gaussian_label((8, 6), 1.0)
    assert np.all(even[3] == 0)  # for even sizes one row (displacement +4) stays empty, as in the authors' code
    # the width: exp(-d^2 / (2 sigma^2)) at a displacement of d cells from the peak, on each axis
    np.testing.assert_allclose([label[55, 42], label[56, 1], label[53, 38]],
                               np.exp(-np.array([1, 4, 9 + 16]) / (2 * 1.5**2)))


@pytest.mark.parametrize("shift", [(0, 0), (3, -2), (-5, 4), (6, 6)])
def test_shifted_patch_is_found_at_the_right_offset(shift):
    rng = np.random.default_rng(2)
    grid = (48, 40)
    base = rng.random((60, 60))
    x = base[6:54, 10:50][None].copy()
    # the same texture, moved by `shift` cells inside the window
    z = base[6 - shift[0]:54 - shift[0], 10 - shift[1]:50 - shift[1]][None].copy()
    bank = CorrelatorBank(GaussianKernel(0.5), gaussian_label(grid, 1.0), 1e-4, 0.01)
    bank.train(x)
    cropped = crop_centre(bank.response(z), 21)
    np.testing.assert_array_equal(peak_offset(cropped), shift)


def test_weighted_channel_sum_equals_sum_of_weighted_channel_responses():
    rng = np.random.default_rng(3)
    x = rng.random((4, 16, 12)).astype(np.float32)
    z = rng.random((4, 16, 12)).astype(np.float32)
    bank = CorrelatorBank(PolynomialKernel(1.0, 2.0), gaussian_label((16, 12), 1.0), 1e-4, 0.01)
    bank.train(x)
    weights = np.array([0.5, 1.0, 2.0, 0.0])
    per_channel = sfft.irfft2(bank.channel_response_hats(z), s=(16, 12))
    np.testing.assert_allclose(bank.response(z, weights), np.tensordot(weights, per_channel, 1), atol=1e-4)


def _direct_pooled_response(bank, z, weights, sigma=None, poly=None):
    """The multi-channel kernel written out in space, with full complex FFTs: k[t] over all channels at once."""
    channels, n = z.shape[-3], z.shape[-2] * z.shape[-1]
    x = bank.model_x
    cross = sum(np.real(np.fft.ifft2(np.fft.fft2(z[..., d, :, :]) * np.conj(np.fft.fft2(x[d]))))
                for d in range(channels))
    if sigma is not None:
        sq = np.sum(z**2, axis=(-3, -2, -1))[..., None, None] + np.sum(x**2)
        kernel = np.exp(-(sq - 2 * cross) / (sigma**2 * n * channels))
    else:
        kernel = (cross / (n * channels) + poly[0]) ** poly[1]
    full_filters = np.stack([np.fft.fft2(sfft.irfft2(w, s=z.shape[-2:])) for w in bank.model_filter_hat])
    return np.real(np.fft.ifft2(np.fft.fft2(kernel) * np.tensordot(weights, full_filters, 1)))


@pytest.mark.parametrize("kernel", [GaussianKernel(0.5), PolynomialKernel(1.0, 2.0)])
def test_pooled_kernel_response_is_the_multi_channel_kernel_under_the_weighted_filters(kernel):
    rng = np.random.default_rng(4)
    x = rng.random((5, 16, 12)).astype(np.float32) * 0.3
    z = rng.random((3, 5, 16, 12)).astype(np.float32) * 0.3  # three samples at once, as the context patches
    bank = CorrelatorBank(kernel, gaussian_label((16, 12), 1.0), 1e-4, 0.01)
    bank.train(x)
    weights = np.array([0.5, 1.0, 2.0, 0.0, 1.5])
    poly = None if isinstance(kernel, GaussianKernel) else (kernel.offset, kernel.degree)
    expected = _direct_pooled_response(bank, z.astype(np.float64), weights, getattr(kernel, "sigma", None), poly)
    pooled = bank.pooled_kernel_response(z, weights)
    assert pooled.shape == (3, 16, 12)
    np.testing.assert_allclose(pooled, expected, rtol=1e-3, atol=1e-3 * np.abs(expected).max())  # float32
    # one channel: pooling changes nothing
    single = CorrelatorBank(kernel, gaussian_label((16, 12), 1.0), 1e-4, 0.01)
    single.train(x[:1])
    np.testing.assert_allclose(single.pooled_kernel_response(z[:, :1]), single.response(z[:, :1]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kernel", [GaussianKernel(0.5), PolynomialKernel(1.0, 2.0)])
@pytest.mark.parametrize("sigma", [1.0, 6.0])  # a TACF-like label, and one too wide for its grid
def test_self_response_maxima_and_means_are_those_of_the_maps(kernel, sigma):
    rng = np.random.default_rng(5)
    grid = (15, 12)
    x = rng.random((3, *grid)).astype(np.float32)
    bank = CorrelatorBank(kernel, gaussian_label(grid, sigma), 1e-4, 0.01)
    assert bank._self_responses_peak_at_label == (sigma == 1.0)
    contexts = 0.5 * rng.random((2, 3, *grid)).astype(np.float32)
    for context_energy in (None, bank.context_energy(contexts)):
        bank.train(x, context_energy)
        filter_hat, kernel_hat = bank._fresh
        maps = sfft.irfft2(filter_hat * kernel_hat, s=grid)
        maxima, means = bank.fresh_self_response_maxima_and_means()
        np.testing.assert_allclose(maxima, maps.max(axis=(1, 2)), rtol=1e-5)
        np.testing.assert_allclose(means, maps.mean(axis=(1, 2)), rtol=1e-5, atol=1e-7)
        if sigma == 1.0:  # the maps peak where the label does: (H-1, W-1)
            assert all(np.unravel_index(np.argmax(m), grid) == (14, 11) for m in maps)


def test_model_is_an_exponential_moving_average():
    rng = np.random.default_rng(4)
    first, second = rng.random((2, 1, 10, 10))
    bank = CorrelatorBank(GaussianKernel(0.5), gaussian_label((10, 10), 1.0), 1e-4, learning_rate=0.25)
    bank.train(first)
    bank.train(second)
    np.testing.assert_allclose(bank.model_x, 0.75 * first + 0.25 * second)


def _exact_gaussian_kernel(sigma: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """k(a_d, b_d) per channel, written out in float64: exp(-(|a|^2 + |b|^2 - 2 a * b) / (sigma^2 N))."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    n = a.shape[-1] * a.shape[-2]
    cross = sfft.irfft2(sfft.rfft2(a) * np.conj(sfft.rfft2(b)), s=a.shape[-2:])
    norms = np.sum(a**2, axis=(-2, -1))[..., None, None] + np.sum(b**2, axis=(-2, -1))[..., None, None]
    return np.exp(-(norms - 2 * cross) / (sigma**2 * n))


def _exact_context_energy(bank: CorrelatorBank, contexts: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """sum_s |F(k(p_s x_s, p_s x_s))|^2 through the exact kernel, in float64."""
    scaled = contexts.astype(np.float64) * scales[:, None, None, None]
    kernel_hat = sfft.rfft2(_exact_gaussian_kernel(bank.kernel.sigma, scaled, scaled))
    return np.sum(np.abs(kernel_hat) ** 2, axis=0)


def test_context_energy_of_small_scaled_patches_matches_the_exact_kernel():
    """Context patches scaled by ~1/16 (as in training) take the closed first-order form: it agrees with the
    exact kernel to far better than the context term's own size at every frequency."""
    rng = np.random.default_rng(3)
    grid = (24, 30)
    contexts = (0.1 * rng.random((4, 3, *grid))).astype(np.float32)  # fHOG-like values, windowed
    scales = np.array([0.05, 0.1, 0.0625, 0.08])
    bank = CorrelatorBank(GaussianKernel(0.5), gaussian_label(grid, 1.0), 1e-4, 0.01)
    exponent_bound = 4 * np.max(np.sum((contexts * scales[:, None, None, None]) ** 2, axis=(-2, -1))) / (0.25 * 720)
    assert exponent_bound < 4.5e-3  # the closed form applies
    energy = bank.context_energy(contexts, scales=scales)
    exact = _exact_context_energy(bank, contexts, scales)
    np.testing.assert_allclose(energy[:, 0, 0], exact[:, 0, 0], rtol=1e-6)  # the DC term: ~ (S N)^2
    off_dc = np.ones(exact.shape, bool)
    off_dc[:, 0, 0] = False
    assert np.max(np.abs(energy - exact)[off_dc]) < 1e-3 * np.max(exact[off_dc])


def test_context_energy_of_large_patches_takes_the_exact_kernel():
    rng = np.random.default_rng(4)
    grid = (16, 20)
    contexts = rng.random((2, 3, *grid)).astype(np.float32)
    scales = np.array([1.0, 0.5])
    bank = CorrelatorBank(GaussianKernel(0.5), gaussian_label(grid, 1.0), 1e-4, 0.01)
    power = np.abs(sfft.rfft2(contexts)) ** 2
    sq_norms = np.sum(contexts.astype(np.float64) ** 2, axis=(-2, -1))[..., None, None]
    assert bank.kernel.first_order_kernel_hat(power, sq_norms, sq_norms, 320) is None  # exponent far above the bound
    exact = _exact_context_energy(bank, contexts, scales)
    np.testing.assert_allclose(bank.context_energy(contexts, scales=scales), exact, rtol=1e-4,
                               atol=1e-6 * exact.max())  # float32 against float64


def test_pooled_and_per_channel_responses_both_answer_a_copy_of_the_template_most():
    """What the challenge factors need of either form: a context patch like the target gets the sharper response."""
    rng = np.random.default_rng(5)
    texture = lambda: cv2.GaussianBlur(rng.integers(0, 256, (96, 96, 3), dtype=np.uint8), (0, 0), 2)
    target, other = texture(), texture()
    window = np.outer(np.hanning(24), np.hanning(24)).astype(np.float32)
    x = fhog(target, 4, divisor=255.0) * window
    bank = CorrelatorBank(GaussianKernel(0.5), gaussian_label((24, 24), 24 / 40), 1e-4, 0.01)
    bank.train(x)
    samples = np.stack([fhog(target, 4, divisor=255.0), fhog(other, 4, divisor=255.0)]) * window
    for respond in (bank.response, bank.pooled_kernel_response):
        copy_response, other_response = (crop_centre(r, 11) for r in respond(samples))
        assert pme(copy_response) > 3 * pme(other_response)
        assert np.unravel_index(np.argmax(copy_response), (11, 11)) == (5, 5)


def _fhog_like(rng, shape) -> np.ndarray:
    """Values like windowed fHOG channels (0 to 0.2, under a Hann window), whose Gaussian kernel stays near 1."""
    window = np.outer(np.hanning(shape[-2]), np.hanning(shape[-1]))
    return (0.2 * rng.random(shape) * window).astype(np.float32)


def test_fast_kernel_is_the_gaussian_to_within_its_second_order_term():
    """TrackerConfig.fast_kernel: under FAST_KERNEL_EXPONENT the kernel's first-order form 1 - u, transformed in
    closed form, is within u^2 / 2 of exp(-u) at every displacement, with u the exact exponent."""
    rng = np.random.default_rng(5)
    a, b = _fhog_like(rng, (31, 24, 30)), _fhog_like(rng, (31, 24, 30))
    kernel = GaussianKernel(0.5, FAST_KERNEL_EXPONENT)
    norms_a, norms_b = (np.sum(v.astype(np.float64) ** 2, axis=(-2, -1))[..., None, None] for v in (a, b))
    kernel_hat = kernel.first_order_kernel_hat(sfft.rfft2(a) * np.conj(sfft.rfft2(b)), norms_a, norms_b, 720)
    assert kernel_hat is not None
    exact = _exact_gaussian_kernel(0.5, a, b)
    exponent = -np.log(exact)
    assert 0.01 < exponent.max() < FAST_KERNEL_EXPONENT  # well past the context energy's 4.5e-3, under the bound
    first_order = sfft.irfft2(kernel_hat, s=(24, 30))
    np.testing.assert_allclose(first_order, 1 - exponent, atol=1e-6)
    assert np.all(np.abs(first_order - exact) <= exponent**2 / 2 + 1e-6)


def test_fast_kernel_takes_the_exact_kernel_above_its_bound():
    rng = np.random.default_rng(6)
    a = 5 * _fhog_like(rng, (3, 24, 30))
    norms = np.sum(a.astype(np.float64) ** 2, axis=(-2, -1))[..., None, None]
    assert 4 * norms.max() / (0.25 * 720) > FAST_KERNEL_EXPONENT
    assert GaussianKernel(0.5, FAST_KERNEL_EXPONENT).first_order_kernel_hat(
        np.abs(sfft.rfft2(a)) ** 2, norms, norms, 720) is None
    bank = CorrelatorBank(GaussianKernel(0.5, FAST_KERNEL_EXPONENT), gaussian_label((24, 30), 1.0), 1e-4, 0.01)
    np.testing.assert_allclose(sfft.irfft2(bank.auto_kernel_hat(a, sfft.rfft2(a)), s=(24, 30)),
                               _exact_gaussian_kernel(0.5, a, a), atol=1e-5)


@pytest.mark.parametrize("shift", [(3, -2), (-5, 4)])
def test_the_fast_kernel_finds_a_shifted_patch_where_the_exact_one_does(shift):
    rng = np.random.default_rng(2)
    base = 0.2 * rng.random((31, 60, 60))
    window = np.outer(np.hanning(48), np.hanning(40))
    x = base[:, 6:54, 10:50] * window
    z = base[:, 6 - shift[0]:54 - shift[0], 10 - shift[1]:50 - shift[1]] * window
    responses = []
    for kernel in (GaussianKernel(0.5), GaussianKernel(0.5, FAST_KERNEL_EXPONENT)):
        bank = CorrelatorBank(kernel, gaussian_label((48, 40), 1.0), 1e-4, 0.01)
        bank.train(x)
        responses.append(crop_centre(bank.response(z), 21))
        np.testing.assert_array_equal(peak_offset(responses[-1]), shift)
    exact, fast = responses
    assert np.max(np.abs(fast - exact)) < 0.05 * np.max(exact)
