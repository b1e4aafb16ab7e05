"""Generated test sequences, shared by the tests of the trackers."""
import cv2
import numpy as np

from tacf.eval.metrics import box_iou


def texture(rng, shape, blur=3):
    noise = rng.integers(0, 256, size=shape, dtype=np.uint8)
    return cv2.GaussianBlur(noise, (0, 0), blur)


def moving_target_sequence(frames=40, size=(240, 320), target=(30, 24), velocity=(2.0, 3.0), gray=False,
                           steps=None):
    """A textured target sliding over a textured background; returns frames and 0-based (x, y, w, h) truth.
    `steps`, a list of (row, col) moves, one after each frame, replaces the constant velocity (and `frames`)."""
    if steps is None:
        steps = [velocity] * frames
    rng = np.random.default_rng(7)
    channels = () if gray else (3,)
    background = texture(rng, size + channels, blur=4)
    sprite = texture(rng, target + channels, blur=1)
    sprite = cv2.add(sprite, 60)  # brighter than the background, as a vehicle on a road
    y, x = 60.0, 50.0
    images, boxes = [], []
    for step in steps:
        image = background.copy()
        top, left = int(round(y)), int(round(x))
        visible = image[top:top + target[0], left:left + target[1]]  # clipped at the image border
        visible[...] = sprite[:visible.shape[0], :visible.shape[1]]
        images.append(image)
        boxes.append((left, top, target[1], target[0]))
        y, x = y + step[0], x + step[1]
    return images, np.array(boxes, dtype=float)


def leaving_sequence(direction, size=(240, 320), target=(16, 20), speed=(2.0, 3.0), seed=7, before=30, after=20):
    """A textured target on a textured background whose centre reaches the frame's edge, or corner, after `before`
    frames, moving `speed` (rows, cols) a frame in `direction` (-1, 0 or 1 on each axis: (1, 1) leaves through the
    bottom-right corner), then `after` frames on; returns frames and 0-based (x, y, w, h) truth, part outside."""
    rng = np.random.default_rng(seed)
    background = texture(rng, size + (3,), blur=4)
    sprite = cv2.add(texture(rng, target + (3,), blur=1), 60)
    step = np.multiply(direction, speed)
    end = np.array(size) * (np.array(direction) + 1) / 2  # the edge, or corner, the target leaves through
    images, boxes = [], []
    for k in range(before + after):
        top_left = np.round(end + (k - before) * step - np.array(target) / 2).astype(int)
        first, last = np.maximum(top_left, 0), np.minimum(top_left + target, size)  # the part still in the frame
        image = background.copy()
        if np.all(first < last):
            image[first[0]:last[0], first[1]:last[1]] = sprite[first[0] - top_left[0]:last[0] - top_left[0],
                                                               first[1] - top_left[1]:last[1] - top_left[1]]
        images.append(image)
        boxes.append((top_left[1], top_left[0], target[1], target[0]))
    return images, np.array(boxes, dtype=float)


def assert_follows(results, truth):
    """The boxes of results (one per frame after the first) stay on the generated target, to its last frames."""
    overlaps = [box_iou(r.box, t) for r, t in zip(results, truth[1:])]
    assert np.mean(overlaps) > 0.6, overlaps
    assert min(overlaps[-10:]) > 0.4, overlaps
