"""The correlators' 2-D real FFTs over the last two axes: scipy.fft's, called without its Python wrappers.

scipy.fft.rfft2 / irfft2 check and normalise their arguments and dispatch through a backend registry before reaching
pocketfft: about 8 us a call against 2 for pocketfft's own entry point, and the correlators make about 12 of these
calls a frame (17 before `fast_kernel`). That entry point is private to scipy (unchanged in signature since scipy
1.4), so the public functions serve whenever it is missing or the arguments are not the plain case;
tests/test_fft.py checks that both give the same bits. `squared_magnitude` is the |spectrum|^2 every filter's
denominator needs.
"""
from __future__ import annotations

import numpy as np
import scipy.fft

try:
    from scipy.fft._pocketfft.pypocketfft import c2r as _pocketfft_c2r, r2c as _pocketfft_r2c
except ImportError:  # a scipy without it: the public functions
    _pocketfft_c2r = _pocketfft_r2c = None

_NO_NORMALISATION, _DIVIDE_BY_N = 0, 2  # pocketfft's `inorm`: scipy's norm="backward" forward and inverse


def rfft2(x: np.ndarray) -> np.ndarray:
    """scipy.fft.rfft2(x, axes=(-2, -1))."""
    if _pocketfft_r2c is None or x.dtype not in (np.float32, np.float64) or x.ndim < 2:
        return scipy.fft.rfft2(x, axes=(-2, -1))
    return _pocketfft_r2c(x, (x.ndim - 2, x.ndim - 1), True, _NO_NORMALISATION, None, 1)


def squared_magnitude(x_hat: np.ndarray) -> np.ndarray:
    """|x_hat|^2 element by element, without np.abs's square root; a real array (a spectrum known to be real, such
    as a power spectrum or a closed-form auto-kernel's) is squared as it is."""
    if np.iscomplexobj(x_hat):
        return x_hat.real**2 + x_hat.imag**2
    return x_hat**2


def irfft2(x_hat: np.ndarray, grid_hw: tuple[int, int]) -> np.ndarray:
    """scipy.fft.irfft2(x_hat, s=grid_hw, axes=(-2, -1)) of a half spectrum (..., H, W // 2 + 1)."""
    height, width = int(grid_hw[0]), int(grid_hw[1])
    if (_pocketfft_c2r is None or x_hat.dtype not in (np.complex64, np.complex128) or x_hat.ndim < 2
            or x_hat.shape[-2:] != (height, width // 2 + 1)):
        return scipy.fft.irfft2(x_hat, s=(height, width), axes=(-2, -1))
    return _pocketfft_c2r(x_hat, (x_hat.ndim - 2, x_hat.ndim - 1), width, False, _DIVIDE_BY_N, None, 1)
