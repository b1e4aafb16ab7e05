"""A generated aerial-looking scene with one moving textured target and its exact ground-truth box per frame.

Deterministic: frame i and box i depend only on the Scene's fields and i, so tests and the demo can check that
the boxes the service returns follow the target. The camera pans slowly over a textured terrain (colour blobs
at several scales, fine grain, four straight roads); the target is a striped "vehicle" that moves on a Lissajous
path (at most 3.6 px per frame at the default 640x360, on whole pixels) and changes size by about +-10%.
"""
from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from tacf_clients.sources import FrameSource, SourceFrame, never_stop
from tacf_schemas.images import check_dimensions

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class Scene:
    width: int = 640
    height: int = 360
    target_w: int = 48
    target_h: int = 36
    period: int = 600          # frames per loop of the target's path (30 s at 20 fps)
    seed: int = 2020

    @classmethod
    def from_spec(cls, spec: str) -> "Scene":
        """``scene`` or ``scene:WIDTHxHEIGHT``."""
        match = re.fullmatch(r"scene(?::(\d+)x(\d+))?", spec)
        if not match:
            raise ValueError(f"scene spec {spec!r}: expected 'scene' or 'scene:WIDTHxHEIGHT'")
        if match.group(1) is None:
            return cls()
        width, height = int(match.group(1)), int(match.group(2))
        if width < 160 or height < 120:
            raise ValueError("scene must be at least 160x120")
        check_dimensions(width, height)         # FrameError (a ValueError) beyond what a frame may be on the wire
        scale = min(width / 640, height / 360)
        return cls(width, height, max(12, round(48 * scale)), max(10, round(36 * scale)))

    # --- geometry -------------------------------------------------------------------------------------------
    def box(self, i: int) -> Box:
        """Ground-truth (x, y, w, h) of the target in frame i: 0-based pixels, top-left origin."""
        t = 2 * math.pi * (i % self.period) / self.period
        s = 1.0 + 0.1 * math.sin(2 * t + 0.5)
        w, h = round(self.target_w * s), round(self.target_h * s)
        margin_x, margin_y = 0.30 * self.width, 0.28 * self.height
        cx = self.width / 2 + margin_x * math.sin(t)
        cy = self.height / 2 + margin_y * math.sin(2 * t + 1.0)
        return float(round(cx - w / 2)), float(round(cy - h / 2)), float(w), float(h)

    def _pan(self, i: int) -> tuple[int, int]:
        t = 2 * math.pi * (i % (2 * self.period)) / (2 * self.period)
        ox = self._margin_x * (0.5 + 0.5 * math.sin(t))
        oy = self._margin_y * (0.5 + 0.5 * math.sin(t + 2.0))
        return round(ox), round(oy)

    @property
    def _margin_x(self) -> int:
        return self.width // 4

    @property
    def _margin_y(self) -> int:
        return self.height // 4

    # --- pixels ---------------------------------------------------------------------------------------------
    def frame(self, i: int) -> np.ndarray:
        """Frame i as HxWx3 BGR uint8."""
        ox, oy = self._pan(i)
        image = self._terrain[oy:oy + self.height, ox:ox + self.width].copy()
        x, y, w, h = (int(v) for v in self.box(i))
        patch = cv2.resize(self._target, (w, h), interpolation=cv2.INTER_AREA)
        image[y:y + h, x:x + w] = patch
        return image

    @cached_property
    def _terrain(self) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        H, W = self.height + 2 * self._margin_y, self.width + 2 * self._margin_x
        field = np.zeros((H, W), np.float32)
        for cells, weight in ((6, 1.0), (24, 0.5), (90, 0.25)):
            coarse = rng.standard_normal((cells * H // W + 2, cells + 2)).astype(np.float32)
            field += weight * cv2.resize(coarse, (W, H), interpolation=cv2.INTER_CUBIC)
        field = (field - field.min()) / (np.ptp(field) + 1e-6)
        grass = np.array([60, 120, 70], np.float32)       # BGR
        soil = np.array([70, 110, 150], np.float32)
        image = grass * (1 - field[..., None]) + soil * field[..., None]
        image += rng.normal(0, 9, (H, W, 1)).astype(np.float32)      # grain
        image = np.clip(image, 0, 255).astype(np.uint8)
        for k in range(2):                                           # two roads across, two down
            y0, y1 = int(rng.integers(0, H)), int(rng.integers(0, H))
            cv2.line(image, (0, y0), (W - 1, y1), (150, 150, 150), max(6, H // 40))
            x0 = int(rng.integers(W // 4, 3 * W // 4))
            cv2.line(image, (x0, 0), (x0 + int(rng.integers(-W // 8, W // 8)), H - 1), (140, 145, 150), max(5, H // 50))
        return image

    @cached_property
    def _target(self) -> np.ndarray:
        """The target texture at twice its nominal size (downscaled per frame): a red body with white stripes,
        a dark windscreen and a yellow roof mark."""
        w, h = 2 * self.target_w, 2 * self.target_h
        patch = np.full((h, w, 3), (40, 40, 200), np.uint8)
        for k in range(1, 6, 2):
            x = k * w // 7
            cv2.rectangle(patch, (x, 0), (x + w // 14, h - 1), (245, 245, 245), -1)
        cv2.rectangle(patch, (w // 10, h // 5), (w // 3, 4 * h // 5), (30, 30, 30), -1)
        cv2.circle(patch, (2 * w // 3, h // 2), h // 5, (0, 220, 255), -1)
        cv2.rectangle(patch, (0, 0), (w - 1, h - 1), (20, 20, 20), max(2, h // 12))
        return patch


class SceneSource(FrameSource):
    """The scene as an endless frame source (frame index = position since start)."""

    live = False

    def __init__(self, scene: Scene | None = None, fps: float = 30.0):
        self.scene = scene or Scene()
        self.fps, self.name = fps, f"scene:{self.scene.width}x{self.scene.height}"

    def frames(self, should_stop: Callable[[], bool] = never_stop) -> Iterator[SourceFrame]:
        i = 0
        while True:
            yield SourceFrame(i, self.scene.frame(i), time.time_ns())
            i += 1

