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


def assert_follows(results, truth):
    """The boxes of results (one per frame after the first) stay on the generated target, to its last frames."""
    overlaps = [box_iou(r.box, t) for r, t in zip(results, truth[1:])]
    assert np.mean(overlaps) > 0.6, overlaps
    assert min(overlaps[-10:]) > 0.4, overlaps
