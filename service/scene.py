"""A synthetic video for tests: a textured square moving over a textured background (`tacf demo` and `tacf publish
scene` have their own, tacf_clients.scene).

    scene = MovingTargetScene(1280, 720)
    image, box = scene.frame(i)        # HxWx3 BGR uint8, ground-truth [x, y, w, h]
"""
from __future__ import annotations

import math

import cv2
import numpy as np


class MovingTargetScene:
    def __init__(self, width: int = 640, height: int = 360, target: int = 64, speed: float = 3.0,
                 seed: int = 7) -> None:
        rng = np.random.default_rng(seed)
        noise = rng.integers(0, 256, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8)
        self.background = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
        self.background = cv2.GaussianBlur(self.background, (0, 0), 2.0)
        self.background = (self.background * 0.6 + 50).astype(np.uint8)      # busy but lower contrast
        blocks = rng.integers(0, 256, (6, 6, 3), dtype=np.uint8)                # a distinctive block pattern
        self.target = cv2.resize(blocks, (target, target), interpolation=cv2.INTER_NEAREST)
        cv2.rectangle(self.target, (0, 0), (target - 1, target - 1), (0, 0, 0), 3)
        self.width, self.height, self.size, self.speed = width, height, target, speed

    def box(self, i: int) -> tuple[float, float, float, float]:
        """The target's box on frame i: a smooth loop (speed px/frame at most) inside the frame."""
        span_x, span_y = self.width - self.size - 20, self.height - self.size - 20
        t = i * self.speed / max(span_x, 1)
        x = 10 + span_x * (0.5 + 0.5 * math.sin(t))
        y = 10 + span_y * (0.5 + 0.5 * math.sin(0.7 * t + 1.0))
        return (float(int(x)), float(int(y)), float(self.size), float(self.size))

    def frame(self, i: int) -> tuple[np.ndarray, tuple[float, float, float, float]]:
        box = self.box(i)
        x, y = int(box[0]), int(box[1])
        image = self.background.copy()
        image[y:y + self.size, x:x + self.size] = self.target
        return image, box

