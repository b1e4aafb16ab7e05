"""Staple (Bertinetto et al., CVPR 2016), the scaffolding of the paper's own ablation baseline, as a peer.

The paper's "KCC" baseline (0.374 on UAV123@10fps against TACF's 0.456) is wang-chen/KCC's tracker: Staple with a
kernel cross-correlator for scale only (ALGORITHM.md section 15). TACF kept Staple's areas, crop and histograms
and changed the rest; our `kcc` profile keeps those changes and only switches the three attentions off. This is
the other baseline, so that the paper's comparison can be made here too. With Staple's own parameters (which
section 15 lists as the baseline's): a linear correlation filter with one denominator shared by the 28 channels
(gray + 27 fHOG), padding 1 within 150^2 normalised pixels, and the colour-histogram response *merged* into the
filter's (0.3) rather than used as a window. Scale is Staple's DSST (33 scales, step 1.02), not KCC's kernel
scale correlator: the one departure from the paper's baseline.

Three details follow this project's TACF rather than Staple's code: the box is reported at the current frame's
scale (Staple's lags one frame), the histogram masks keep the first frame's proportions of the normalised
patch (Staple redraws them each frame from areas whose proportions barely change), and the scale filter rests
while the box lies mostly beyond the frame (`scale_min_visible`; Staple's grew it up to 9 times as a target left
through a corner).

Per frame: LOCALISE (filter response, cropped and upsampled; the mean foreground likelihood of every target-sized
window around the last position; their blend's peak), SCALE (DSST), UPDATE (filter, histograms, scale model).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from tacf.attention import pme
from tacf.boxes import box_around, check_box, overlapping
from tacf.colour import ColourModel
from tacf.config import check_fields, shared_combination_problems
from tacf.correlator import gaussian_label
from tacf.features import fhog
from tacf.fft import squared_magnitude
from tacf.geometry import NormalisedGrid, TargetAreas, resize_auto, round_half_up, subwindow
from tacf.response import crop_centre, peak_offset, upsample
from tacf.scale import ScaleFilter
from tacf.tracker import TrackResult, check_frame

HOG_CHANNELS = 27  # Staple keeps fHOG's 18 contrast-sensitive and 9 insensitive orientation channels


@dataclass(frozen=True)
class StapleConfig:
    """Staple's published parameters. The field names are TrackerConfig's where the two mean the same thing,
    so the DSST scale filter reads either."""

    cell_size: int = 4
    fixed_area: float = 150.0**2
    padding: float = 1.0
    inner_padding: float = 0.2
    output_sigma_factor: float = 1.0 / 16
    lambda1: float = 1e-3
    learning_rate: float = 0.01
    merge_factor: float = 0.3  # weight of the colour response in the blend
    hist_bins: int = 32
    hist_learning_rate: float = 0.04
    num_scales: int = 33
    scale_step: float = 1.02
    scale_sigma_factor: float = 0.25
    scale_learning_rate: float = 0.025
    scale_lambda: float = 1e-3
    scale_model_max_area: float = 32.0 * 16
    scale_min_visible: float = 0.5
    fast_resize: bool = False

    def __post_init__(self) -> None:
        check_fields(self, positive=("cell_size", "fixed_area", "padding", "output_sigma_factor",
                                     "scale_sigma_factor", "scale_model_max_area"),
                     rates=("learning_rate", "merge_factor", "hist_learning_rate", "scale_learning_rate",
                            "scale_min_visible"))
        problems = shared_combination_problems(self)
        if problems:
            raise ValueError("StapleConfig: " + "; ".join(problems))


def window_means(likelihood: np.ndarray, window_hw) -> np.ndarray:
    """Mean of `likelihood` over every window_hw window inside it (Staple's centre likelihood), from the integral
    image: shape (H - h + 1, W - w + 1), entry (i, j) for the window whose top-left pixel is (i, j)."""
    h, w = int(window_hw[0]), int(window_hw[1])
    total = cv2.integral(likelihood.astype(np.float64))
    return (total[h:, w:] - total[:-h, w:] - total[h:, :-w] + total[:-h, :-w]) / (h * w)


class Staple:
    """Staple: `init(frame, box)` then `update(frame) -> TrackResult`, like tacf.Tracker. It has no test for a
    lost target: `ok` is always True; `pme` is the blended response's."""

    def __init__(self, config: StapleConfig | None = None):
        self.config = config or StapleConfig()
        self._frame_shape = None

    def init(self, frame: np.ndarray, box) -> None:
        cfg = self.config
        frame = check_frame(frame)
        x, y, w, h = check_box(box, frame.shape)
        self._frame_shape = frame.shape
        self.pos = np.array([y + h / 2, x + w / 2])
        self.target_hw = np.maximum(round_half_up([h, w]), 1.0)
        self.base_target_hw = self.target_hw.copy()
        self.scale_factor = 1.0
        self.areas = self._areas_around(self.target_hw)
        self.grid = NormalisedGrid.from_areas(self.areas, cfg.cell_size)
        self.cosine_window = self.grid.cosine_window()
        sigma = np.sqrt(np.prod(self.grid.target_hw)) * cfg.output_sigma_factor / cfg.cell_size
        self.label_hat = scipy.fft.rfft2(gaussian_label(self.grid.filter_hw, sigma)).astype(np.complex64)
        # The colour response covers every target-sized window whose centre lies in the response square.
        self.colour_area_hw = self.grid.target_hw + self.grid.response_size - 1
        self.numerator = self.denominator = None
        patch = self._sample(frame)
        self.colour = ColourModel(patch, self.grid.patch_hw, self.areas.fg_area * self.areas.resize_factor,
                                  self.target_hw * self.areas.resize_factor, cfg.hist_bins,
                                  cfg.hist_learning_rate, floor=0.0)
        self.scale_filter = ScaleFilter(cfg, frame.shape[:2], self.base_target_hw, self.grid.target_hw,
                                        self.areas.bg_area)
        self._train(frame, patch)

    def update(self, frame: np.ndarray) -> TrackResult:
        if self._frame_shape is None:
            raise RuntimeError("call init(frame, box) before update(frame)")
        frame = check_frame(frame, self._frame_shape)
        cfg = self.config

        # ------- LOCALISE -------
        filter_response = upsample(crop_centre(self._filter_response(self._sample(frame)), self.grid.crop_cells),
                                   self.grid.response_size)
        colour_patch = subwindow(frame, self.pos, self.colour_area_hw,
                                 self.colour_area_hw / self.areas.resize_factor, cfg.fast_resize)
        colour_response = window_means(self.colour.pixel_likelihood(colour_patch), self.grid.target_hw)
        response = (1 - cfg.merge_factor) * filter_response + cfg.merge_factor * colour_response
        displacement = peak_offset(response) / self.areas.resize_factor
        self.pos = overlapping(self.pos + displacement, self.target_hw, frame.shape)

        # ------- SCALE -------
        self.scale_factor = self.scale_filter.estimate(frame, self.pos, self.scale_factor)
        self.target_hw = np.maximum(round_half_up(self.base_target_hw * self.scale_factor), 1.0)
        self.areas = self._areas_around(self.target_hw)
        self.pos = overlapping(self.pos, self.target_hw, frame.shape)

        # ------- UPDATE -------
        patch = self._sample(frame)
        self._train(frame, patch)
        self.colour.update(patch)
        return TrackResult(box=self.box, pme=pme(response), score=float(response.max()), ok=True,
                           scale=self.scale_factor)

    @property
    def box(self) -> tuple[float, float, float, float]:
        return box_around(self.pos, self.target_hw)

    def _areas_around(self, target_hw: np.ndarray) -> TargetAreas:
        cfg = self.config
        return TargetAreas.around(target_hw, cfg.padding, self._frame_shape[:2], cfg.fixed_area, cfg.inner_padding)

    def _sample(self, frame: np.ndarray) -> np.ndarray:
        return subwindow(frame, self.pos, self.grid.patch_hw, self.areas.bg_area, self.config.fast_resize)

    def _features_hat(self, patch: np.ndarray) -> np.ndarray:
        """Spectra of the windowed features: gray (in [-0.5, 0.5]) and fHOG's first 27 channels, (28, H, W // 2 + 1)."""
        cfg = self.config
        hog = fhog(patch, cfg.cell_size)[:HOG_CHANNELS]  # raw 0-255 values, as Staple
        gray = patch if patch.ndim == 2 else cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY)
        gray = resize_auto(gray, self.grid.filter_hw, cfg.fast_resize).astype(np.float32) / 255 - 0.5
        features = np.concatenate([gray[None], hog]) * self.cosine_window
        return scipy.fft.rfft2(features)

    def _filter_response(self, patch: np.ndarray) -> np.ndarray:
        """sum_c conj(H_c) Z_c with H_c = A_c / (B + lambda): one denominator B shared by all channels."""
        spectrum = np.sum(np.conj(self.numerator) * self._features_hat(patch), axis=0)
        return scipy.fft.irfft2(spectrum / (self.denominator + self.config.lambda1), s=self.grid.filter_hw)

    def _train(self, frame: np.ndarray, patch: np.ndarray) -> None:
        cfg = self.config
        features_hat = self._features_hat(patch)
        cells = float(np.prod(self.grid.filter_hw))
        numerator = np.conj(self.label_hat) * features_hat / cells
        denominator = np.sum(squared_magnitude(features_hat), axis=0) / cells
        if self.numerator is None:
            self.numerator, self.denominator = numerator, denominator
        else:
            rate = cfg.learning_rate
            self.numerator = (1 - rate) * self.numerator + rate * numerator
            self.denominator = (1 - rate) * self.denominator + rate * denominator
        self.scale_filter.update_model(frame, self.pos, self.scale_factor)
