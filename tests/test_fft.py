"""tacf.fft: pocketfft's entry points give scipy.fft's results bit for bit, and scipy.fft serves otherwise."""
import numpy as np
import pytest
import scipy.fft

import tacf.fft as fft


@pytest.mark.parametrize("shape", [(50, 54), (31, 60, 45), (4, 31, 27, 25), (2, 3, 1, 8)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_same_bits_as_scipy_fft(shape, dtype):
    x = np.random.default_rng(0).standard_normal(shape).astype(dtype)
    spectrum = fft.rfft2(x)
    expected = scipy.fft.rfft2(x, axes=(-2, -1))
    assert spectrum.dtype == expected.dtype
    np.testing.assert_array_equal(spectrum, expected)
    back = fft.irfft2(spectrum, shape[-2:])
    np.testing.assert_array_equal(back, scipy.fft.irfft2(expected, s=shape[-2:], axes=(-2, -1)))
    np.testing.assert_allclose(back, x, atol=1e-5 if dtype == np.float32 else 1e-12)


def test_non_contiguous_input_and_other_dtypes():
    x = np.random.default_rng(1).standard_normal((6, 40, 36)).astype(np.float32)[::2, :, ::-1]
    np.testing.assert_array_equal(fft.rfft2(x), scipy.fft.rfft2(x, axes=(-2, -1)))
    ints = np.arange(48).reshape(6, 8)
    np.testing.assert_array_equal(fft.rfft2(ints), scipy.fft.rfft2(ints))
    # a spectrum of another width than the grid's half: scipy's cropping / zero-padding rules apply
    wide = scipy.fft.rfft2(np.ones((8, 10)))
    np.testing.assert_array_equal(fft.irfft2(wide, (8, 8)), scipy.fft.irfft2(wide, s=(8, 8)))


def test_public_functions_serve_without_pocketfft(monkeypatch):
    monkeypatch.setattr(fft, "_pocketfft_r2c", None)
    monkeypatch.setattr(fft, "_pocketfft_c2r", None)
    x = np.random.default_rng(2).standard_normal((3, 20, 18)).astype(np.float32)
    np.testing.assert_array_equal(fft.rfft2(x), scipy.fft.rfft2(x, axes=(-2, -1)))
    np.testing.assert_array_equal(fft.irfft2(fft.rfft2(x), (20, 18)),
                                  scipy.fft.irfft2(scipy.fft.rfft2(x, axes=(-2, -1)), s=(20, 18), axes=(-2, -1)))


def test_squared_magnitude_of_complex_and_of_real_spectra():
    rng = np.random.default_rng(7)
    spectrum = (rng.normal(size=(3, 8, 5)) + 1j * rng.normal(size=(3, 8, 5))).astype(np.complex64)
    np.testing.assert_allclose(fft.squared_magnitude(spectrum), np.abs(spectrum) ** 2, rtol=1e-6)
    assert fft.squared_magnitude(spectrum).dtype == np.float32
    real = spectrum.real.copy()
    np.testing.assert_array_equal(fft.squared_magnitude(real), real * real)
