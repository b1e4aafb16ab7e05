"""The TACF tracker: `init(frame, box)` then `update(frame) -> TrackResult`, frame after frame. `update` is
`locate` (LOCALISE and SCALE: the box) then `learn` (UPDATE), for callers that send the box before learning.

Per frame (ALGORITHM.md section 7, with the decisions of section B):
  LOCALISE  sample the search area at the last position; colour-weighted cosine window; per-channel kernel
            correlators for fHOG and Color Names; dimensional attention weights the channels; spatiotemporal
            attention multiplies the channel sum; crop; upsample, fuse the two feature types, take the peak
            (refined between cells). After a fast move, also search where that move continues, and keep the
            search whose HOG response peaks higher.
            A frame that shows nothing of the target (one colour, or one colour where the search ends) is sat
            out: the box stays and nothing is learnt.
  SCALE     DSST scale filter at the new position.
  UPDATE    on context frames, context penalties from the PME ratios of the context patches around the new
            position; train fresh filters (with those patches as hard negatives), blend them into the model,
            update the channel weights, colour histograms and scale model.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from tacf.allocator import keep_freed_memory
from tacf.attention import ContextualAttention, DimensionalAttention, SpatiotemporalAttention, context_offsets, pme
from tacf.attention.spatiotemporal import to_response_origin
from tacf.boxes import box_around, check_box, overlapping, visible_fraction
from tacf.colour import ColourModel
from tacf.config import TrackerConfig
from tacf.correlator import (FAST_KERNEL_EXPONENT, FIRST_ORDER_EXPONENT, CorrelatorBank, GaussianKernel,
                             PolynomialKernel, gaussian_label)
from tacf.features import color_names, fhog, fhog_batch
from tacf.geometry import NormalisedGrid, TargetAreas, round_half_up, search_padding, subwindow
from tacf.response import crop_centre, fuse, fusion_coefficients, peak_offset, subcell_peak_offset, upsample
from tacf.scale import ScaleFilter


@dataclass(frozen=True)
class Detection:
    """One search for the target: where it was centred, what it found, and the state it would leave."""

    centre: np.ndarray  # (row, col) image pixels: the search area's centre
    fused: np.ndarray  # fused, upsampled response over the search square; its centre is the search centre
    offset: np.ndarray  # (row, col) of its peak from the centre, normalised pixels
    hog_response: np.ndarray  # cropped HOG response: the detection score and the context factors' reference
    spatial_maps: dict[str, np.ndarray]  # the spatiotemporal attention's maps, kept if this search is taken

    @property
    def score(self) -> float:
        return float(self.hog_response.max())


@dataclass(frozen=True)
class TrackResult:
    box: tuple[float, float, float, float]  # x, y, w, h: 0-based pixels, top-left origin
    pme: float  # peak-to-median energy of the fused response: high = confident
    score: float  # peak value of the fused response
    ok: bool  # False when the PME falls under TrackerConfig.lost_pme or the box has left the frame (lost_min_visible)
    scale: float  # current size relative to the initial box


MIN_FRAME_SIDE = 3  # with 2 the background area rounds to 0 pixels
# A response of one cell a side has its peak at the centre whatever the frame: the box never moves. The default
# profiles' grids have at least 3 for every box in frames up to 50 times as long as wide; a long thin box in a
# longer strip (3 x 168, 8 x 1,280, 32 x 8,000 pixels) can leave 1.
MIN_CROP_CELLS = 3


def check_frame(frame, expected_shape=None) -> np.ndarray:
    if not isinstance(frame, np.ndarray):
        raise ValueError(f"frame must be a numpy array, got {type(frame).__name__}")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
        raise ValueError(f"frame must be HxW (gray) or HxWx3 (BGR), got shape {frame.shape}")
    if frame.shape[0] < MIN_FRAME_SIDE or frame.shape[1] < MIN_FRAME_SIDE:
        raise ValueError(f"frame is empty or too small (under {MIN_FRAME_SIDE} pixels a side): shape {frame.shape}")
    if frame.dtype != np.uint8:
        raise ValueError(f"frame must be uint8, got {frame.dtype}")
    if expected_shape is not None and frame.shape != expected_shape:
        raise ValueError(f"frame shape {frame.shape} differs from the initial frame's {expected_shape}; "
                         "call init() again for a new video")
    if frame.strides[0] < frame[0].nbytes:  # rows overlapping in memory (a sliding_window_view): OpenCV refuses them
        frame = np.ascontiguousarray(frame)
    return frame


@dataclass(frozen=True)
class Flatness:
    """What counts as one colour: every mean over `block` x `block` pixels within `tolerance` grey levels of the
    image's mean colour, in every channel. A standard deviation over `noise_std` is a picture: the quick answer."""

    block: int
    tolerance: int
    noise_std: float


# A dropout of the video link shows nothing: a frame of one colour, give or take sensor or encoder noise. Tested on
# means over 4x4 pixels, which noise of standard deviation s spreads by s / 4 only, while what shows the least
# structure worth tracking (a target three grey levels above fog) keeps its own. More than 4 is snow, or a picture.
BLANK = Flatness(block=4, tolerance=2, noise_std=4.0)
# The lost part of a corrupt frame is one value that the decoder filled in, to a grey level after JPEG; a camera's
# picture never is, over an area twice the target's size a side, for it has noise. Pixel by pixel, since means
# over blocks took in a tiny target (6x6 pixels, 12 grey levels under a plain sky) with the sky around it. Not for
# a target that showed a fill at init: a box drawn inside a plain roof, saturated or noise-free, is searched for
# by the roof's edges as ever (it drifts across the roof, in and out of the fill).
FILL = Flatness(block=1, tolerance=1, noise_std=1.0)
SURROUND = 2.0          # the area around where a search ends that must not be FILL: the box grown twice a side


def _blank(frame: np.ndarray, pos: np.ndarray, area_hw: np.ndarray) -> bool:
    """Whether the whole frame is one colour, to within noise. The whole frame, not the search area: a target that
    moved out of its search area over a plain sky, or one of a few grey levels in fog, leaves the area nearly
    blank and must still be searched for. The search area first, the quick answer on any ordinary frame (20 us;
    the whole of a 4K colour frame takes 0.6 ms, 4.6 ms when it is blank)."""
    return all(_one_colour(part, BLANK) for part in (_area(frame, pos, area_hw), frame))


def _area(frame: np.ndarray, centre: np.ndarray, hw: np.ndarray) -> np.ndarray:
    """The pixels of `frame` within the (height, width) `hw` around `centre` (row, col), at least one: those at the
    frame's edge nearest to an area wholly outside it (a box as tall as the frame, overlapping it by one row)."""
    top, left = np.clip(np.floor(centre - hw / 2), 0, np.asarray(frame.shape[:2]) - 1).astype(int)
    bottom, right = np.minimum(np.ceil(centre + hw / 2), frame.shape[:2]).astype(int)
    return frame[top:max(bottom, top + 1), left:max(right, left + 1)]


def _one_colour(image: np.ndarray, flatness: Flatness) -> bool:
    colour, spread = cv2.meanStdDev(image)
    if spread.max() > flatness.noise_std:
        return False
    height, width = image.shape[:2]
    if flatness.block > 1:
        image = cv2.resize(image, (max(width // flatness.block, 1), max(height // flatness.block, 1)),
                           interpolation=cv2.INTER_AREA)
    # Bounds in whole grey levels, as the block means are: inRange would round a fractional bound outwards.
    centre = np.round(colour.ravel())
    low, high = centre - flatness.tolerance, centre + flatness.tolerance
    return cv2.countNonZero(cv2.inRange(image, low, high)) == image.shape[0] * image.shape[1]


class Tracker:
    """TACF. Frames are HxWx3 BGR uint8 (OpenCV order) or HxW uint8 grayscale."""

    def __init__(self, config: TrackerConfig | None = None):
        if config is not None and not isinstance(config, TrackerConfig):
            raise TypeError(f"config must be a TrackerConfig (a profile: TrackerConfig.profile('kcc')), "
                            f"got {type(config).__name__}")
        self.config = config or TrackerConfig.profile()
        self._frame_shape = None
        self._to_learn = None  # (frame, object_response) of a locate() not yet followed by learn()
        keep_freed_memory()  # per-frame temporaries are megabytes: reuse them, don't map them anew (allocator.py)

    # ------------------------------------------------------------------------------------------------------
    def init(self, frame: np.ndarray, box) -> None:
        """Start (or restart) tracking the target in box = (x, y, w, h) of this frame."""
        cfg = self.config
        frame = check_frame(frame)
        x, y, w, h = check_box(box, frame.shape)
        image_hw = frame.shape[:2]
        # Sizes are whole pixels, as the authors' target_sz: the box reported is the rounded one.
        target_hw = np.maximum(round_half_up([h, w]), 1.0)
        padding = search_padding(target_hw, cfg.fixed_area)
        areas = TargetAreas.around(target_hw, padding, image_hw, cfg.fixed_area, cfg.inner_padding)
        grid = NormalisedGrid.from_areas(areas, cfg.cell_size, cfg.fast_fft)
        if grid.crop_cells < MIN_CROP_CELLS:   # refused before any state changes: a running target is kept
            raise ValueError(f"box {(float(x), float(y), float(w), float(h))} in the {frame.shape[1]}x"
                             f"{frame.shape[0]} image: its search area's response would be {grid.crop_cells} "
                             f"cell(s) a side, under {MIN_CROP_CELLS}, and the box could not move; use a larger "
                             f"frame or more filter cells (fixed_area / cell_size**2)")
        self._frame_shape = frame.shape
        self._to_learn = None
        self.frame_number = 1
        self.pos = np.array([y + h / 2, x + w / 2])
        self.target_hw, self.base_target_hw = target_hw, target_hw.copy()
        self.plain_target = self._shows_fill(frame, self.pos)  # drawn on a fill: a fill later is no dropout
        self.scale_factor = 1.0
        self.displacement = None  # last frame's motion in image pixels (for the motion term)
        self.padding, self.areas, self.grid = padding, areas, grid
        grid_hw = self.grid.filter_hw
        self.cosine_window = self.grid.cosine_window()
        # The paper's spatial attention windows the response with hann alone, centred on zero displacement.
        self.response_window = to_response_origin(self.cosine_window)

        sigma_base = math.sqrt(float(np.prod(self.grid.target_hw))) / cfg.cell_size
        first_order_below = FAST_KERNEL_EXPONENT if cfg.fast_kernel else FIRST_ORDER_EXPONENT
        hog_kernel = GaussianKernel(cfg.hog_kernel_sigma, first_order_below)
        self.banks = {"hog": CorrelatorBank(hog_kernel,
                                            gaussian_label(grid_hw, sigma_base * cfg.hog_output_sigma_factor),
                                            cfg.lambda1, cfg.learning_rate)}
        if cfg.use_colour_names:
            self.banks["cn"] = CorrelatorBank(PolynomialKernel(cfg.cn_poly_a, cfg.cn_poly_b),
                                              gaussian_label(grid_hw, sigma_base * cfg.cn_output_sigma_factor),
                                              cfg.lambda1, cfg.learning_rate)
        channels = {"hog": 31, "cn": 11}
        self.dimensional = {name: DimensionalAttention(channels[name], cfg.dim_threshold, cfg.dim_floor,
                                                       cfg.dim_learning_rate) for name in self.banks}
        self.spatiotemporal = {name: SpatiotemporalAttention(cfg.spatial_learning_rate, cfg.motion_gain,
                                                             cfg.motion_term_wraps) for name in self.banks}
        self.contextual = ContextualAttention(cfg.context_interval, cfg.context_penalty_total,
                                              cfg.context_challenge_floor, cfg.context_penalty_rate,
                                              cfg.context_lambda2)
        self.colour = None
        self.scale_filter = None
        if cfg.scale_estimation:
            self.scale_filter = ScaleFilter(cfg, image_hw, self.base_target_hw, self.grid.target_hw,
                                            self.areas.bg_area)
        self._train(frame)

    def update(self, frame: np.ndarray) -> TrackResult:
        """Locate the target in the next frame, then learn from it."""
        result = self.locate(frame)
        self.learn()
        return result

    def locate(self, frame: np.ndarray) -> TrackResult:
        """The first half of update(): the target's box in the next frame, before the model learns from it.

        Call learn() next. A service can send the box between the two, so that its latency excludes the model
        update (about half of a frame's time, and all of the context frames' extra work); the boxes are those of
        update(). A locate() not preceded by learn() learns from the previous frame first. The frame is read again
        by learn(), so its buffer must not be overwritten in between (a reader filling one array in place).
        """
        if self._frame_shape is None:
            raise RuntimeError("call init(frame, box) before update(frame)")
        frame = check_frame(frame, self._frame_shape)
        self.learn()
        if _blank(frame, self.pos, self._sample_hw()):
            # A dropout frame (black, grey, saturated) shows nothing to track: the box stays and the model does
            # not learn a blank target. Searched, it drifted half a cell a frame (the response window's two equal
            # peaks, on an even grid: zero and one cell) and the motion term carried it on.
            return self._nothing_seen()
        self.frame_number += 1

        # ------- LOCALISE -------
        detection = self._localise(frame, self.pos)
        ahead = self._motion_search_centre()
        if ahead is not None:
            detection = max(detection, self._localise(frame, ahead), key=lambda d: d.score)
        found = detection.centre + detection.offset / self.areas.resize_factor
        position = overlapping(found, self.target_hw, self._frame_shape)
        if not self.plain_target and self._shows_fill(frame, position):
            # A partial dropout (a grey slice of a corrupt frame) over the target: as on a blank frame. Searched
            # and learnt, the box slid to the slice's edges and learnt them (building5, 10 frames: IoU 0.85 -> 0).
            self.frame_number -= 1
            return self._nothing_seen()
        for name, spatial_map in detection.spatial_maps.items():
            self.spatiotemporal[name].keep(spatial_map)
        self.displacement = found - self.pos
        self.pos = position

        # ------- SCALE -------
        if self.scale_filter is not None:
            self.scale_factor = self.scale_filter.estimate(frame, self.pos, self.scale_factor)
            self.target_hw = np.maximum(round_half_up(self.base_target_hw * self.scale_factor), 1.0)
            self.areas = self._areas_around(self.target_hw)
            self.pos = overlapping(self.pos, self.target_hw, self._frame_shape)  # a shrunk box may have to come in

        self._to_learn = frame, detection.hog_response
        confidence = pme(detection.fused)
        # A PME of 0 is a response without a peak (flat, or not finite), and the box did not move: never ok. Nor is
        # a box almost wholly beyond the frame, where a target that has left leaves it (TrackerConfig.lost_min_visible).
        in_view = visible_fraction(self.pos, self.target_hw, self._frame_shape) >= self.config.lost_min_visible
        return TrackResult(box=self.box, pme=confidence, score=float(detection.fused.max()),
                           ok=confidence > 0 and confidence >= self.config.lost_pme and in_view,
                           scale=self.scale_factor)

    def _shows_fill(self, frame: np.ndarray, pos: np.ndarray) -> bool:
        """Whether the box around pos, grown SURROUND times a side, is one flat fill (FILL)."""
        return _one_colour(_area(frame, pos, SURROUND * self.target_hw), FILL)

    def _nothing_seen(self) -> TrackResult:
        """The result of a frame that shows nothing of the target: the box where it was, not ok."""
        return TrackResult(box=self.box, pme=0.0, score=0.0, ok=False, scale=self.scale_factor)

    def learn(self) -> None:
        """The second half of update(): learn from the frame of the last locate(); nothing if done already."""
        if self._to_learn is None:
            return
        frame, object_response = self._to_learn
        self._to_learn = None
        # ------- UPDATE -------
        self._train(frame, object_response)

    @property
    def box(self) -> tuple[float, float, float, float]:
        if self._frame_shape is None:
            raise RuntimeError("no box before init(frame, box)")
        return box_around(self.pos, self.target_hw)

    # ------------------------------------------------------------------------------------------------------
    def _areas_around(self, target_hw: np.ndarray) -> TargetAreas:
        return TargetAreas.around(target_hw, self.padding, self._frame_shape[:2], self.config.fixed_area,
                                  self.config.inner_padding)

    def _sample_hw(self) -> np.ndarray:
        """The image area a sample covers: the background area, grown with the fast-FFT grid."""
        return self.areas.bg_area * self.grid.sample_growth

    def _sample(self, frame: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return subwindow(frame, pos, self.grid.patch_hw, self._sample_hw(), self.config.fast_resize)

    def _motion_search_centre(self) -> np.ndarray | None:
        """Where the last move, continued, puts the target, when that move was fast enough to be worth a second
        search: more than motion_search_threshold of the search radius. At 10 fps a vehicle moves by half its
        length between frames (truck2: 20-23 px for a 45 px truck); a search centred on its last position
        then finds it far out, where the cosine window has dimmed it and the static background's answer at
        zero motion outweighs it, and each frame's shortfall puts it further out (docs/decisions.md)."""
        if not self.config.motion_search or self.frame_number < 3:
            return None
        move = np.hypot(*self.displacement) * self.areas.resize_factor  # normalised pixels
        if move <= self.config.motion_search_threshold * self.grid.response_size / 2:
            return None
        return self.pos + self.displacement

    def _features(self, patch: np.ndarray, names) -> dict[str, np.ndarray]:
        extractors = {"hog": lambda p: fhog(p, self.config.cell_size, divisor=255.0),
                      "cn": lambda p: color_names(p, self.config.cell_size)}
        return {name: extractors[name](patch) for name in names}

    def _patch_and_features(self, frame: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The sample around centre at the current area, and its features."""
        patch = self._sample(frame, centre)
        return patch, self._features(patch, self.banks)

    def _localise(self, frame: np.ndarray, centre: np.ndarray) -> Detection:
        """Search the area around centre with the current model; nothing of the tracker's state changes."""
        cfg = self.config
        patch, features = self._patch_and_features(frame, centre)
        window = self.cosine_window
        if self.colour is not None:
            window = window * self.colour.likelihood_window(patch, self.grid.filter_hw)
        cropped, spatial_maps = {}, {}
        for name, bank in self.banks.items():
            weights = self.dimensional[name].weights if cfg.dimensional_attention else None
            response = bank.response(features[name] * window, weights)
            if cfg.spatiotemporal_attention:
                motion = self.displacement if self.frame_number >= 3 else None
                spatial_maps[name] = self.spatiotemporal[name].propose(response, self.response_window, motion,
                                                                        self.target_hw)
                response = response * spatial_maps[name]
            cropped[name] = crop_centre(response, self.grid.crop_cells)
        size = self.grid.response_size
        upsampled = [upsample(r, size) for r in cropped.values()]
        coefficients = fusion_coefficients(upsampled)
        fused = fuse(upsampled, coefficients)
        if cfg.subcell_peak:
            # Upsampling is linear: the same coefficients fuse the cell-level maps into the map fused was drawn from.
            offset = subcell_peak_offset(fuse(list(cropped.values()), coefficients)) * size / self.grid.crop_cells
        else:
            offset = peak_offset(fused)
        return Detection(np.asarray(centre, dtype=np.float64), fused, offset, cropped["hog"], spatial_maps)

    def _context_features(self, frame: np.ndarray) -> np.ndarray:
        """Windowed fHOG of the four context patches around the current position: (4, 31, H, W).

        With fast_context they are cut from the fHOG of one sample that covers all four: the search area grown on
        each side by the context offset, rounded to whole cells. For a target with padding 3 that is the fHOG of
        about 2.4 search areas instead of 4; the patches' border cells, which the cosine window all but removes,
        then see the pixels beyond them."""
        cell = self.config.cell_size
        offsets = context_offsets(self.target_hw)
        if not self.config.fast_context:
            patches = np.stack([self._sample(frame, self.pos + offset) for offset in offsets])
            return fhog_batch(patches, cell, divisor=255.0) * self.cosine_window
        sample_hw = self._sample_hw()
        grid_per_image_pixel = self.grid.patch_hw / sample_hw
        offset_cells = (np.sign(offsets) * round_half_up(np.abs(offsets) * grid_per_image_pixel / cell)).astype(int)
        margin = np.abs(offset_cells).max(axis=0) * cell  # rows, cols of the covering sample beyond the search area
        union = subwindow(frame, self.pos, self.grid.patch_hw + 2 * margin,
                          sample_hw + 2 * margin / grid_per_image_pixel, self.config.fast_resize)
        features = fhog(union, cell, divisor=255.0)
        rows, cols = self.grid.filter_hw
        corners = margin // cell + offset_cells  # each context patch's first cell in the covering sample
        return np.stack([features[:, r:r + rows, c:c + cols] for r, c in corners]) * self.cosine_window

    def _update_context_penalties(self, context: np.ndarray, context_hat: np.ndarray,
                                  object_response: np.ndarray) -> None:
        """Challenge factors: how strongly the HOG filter answers each context patch, relative to the target."""
        weights = self.dimensional["hog"].weights if self.config.dimensional_attention else None
        hog = self.banks["hog"]
        respond = hog.pooled_kernel_response if self.config.context_pooled_kernel else hog.response
        responses = respond(context, weights, context_hat)
        context_pmes = [pme(crop_centre(response, self.grid.crop_cells)) for response in responses]
        self.contextual.update_penalties(pme(object_response), np.array(context_pmes))

    def _train(self, frame: np.ndarray, object_response: np.ndarray | None = None) -> None:
        """Learn at the current position. On context frames the four context patches around it serve twice:
        the model not yet updated measures their challenge factors (the penalties, given object_response,
        the cropped HOG response of this frame's detection), then they enter the HOG filter as hard negatives.
        The authors' code measures the penalties on patches around the previous position; sampling once saves
        four fHOGs per context frame, and the boxes on the ten UAV sequences come out identical."""
        cfg = self.config
        patch, features = self._patch_and_features(frame, self.pos)
        context_energy = None
        if cfg.context_attention and self.contextual.is_context_frame(self.frame_number):
            hog = self.banks["hog"]
            context = self._context_features(frame)
            context_hat = hog.spectrum(context)
            if object_response is not None:
                self._update_context_penalties(context, context_hat, object_response)
            context_energy = hog.context_energy(context, context_hat, self.contextual.feature_scales())
        for name, bank in self.banks.items():
            bank.train(features[name] * self.cosine_window, context_energy if name == "hog" else None)
            if cfg.dimensional_attention:
                self.dimensional[name].update(*bank.fresh_self_response_maxima_and_means())
        if cfg.colour_window:
            if self.colour is None:
                self.colour = ColourModel(patch, self.grid.patch_hw,
                                          self.areas.fg_area * self.areas.resize_factor,
                                          self.target_hw * self.areas.resize_factor,
                                          cfg.hist_bins, cfg.hist_learning_rate, cfg.likelihood_floor)
            else:
                self.colour.update(patch)
        if self.scale_filter is not None:
            self.scale_filter.update_model(frame, self.pos, self.scale_factor)


@functools.cache   # once a process; a worker forked from a process that ran it inherits the loops compiled
def compile_loops() -> None:
    """Run a Tracker untimed on a small generated frame, init and one update, so that numba compiles every loop it
    calls (fHOG's, the colour lookup's), or loads them from its disk cache, before a live frame waits on them.
    Compiled at a session's first frame instead, the colour lookup alone held the first box 0.4-0.6 s and dropped
    the frames meanwhile. Gray and colour frames, under every profile, reach the loops with the argument types
    compiled here (tests/test_tracker.py checks)."""
    frame = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    tracker = Tracker()
    tracker.init(frame, (24, 24, 16, 16))
    tracker.update(np.roll(frame, 2, axis=1))
