"""Image files as frames: the suffixes an image folder's frames may carry, and reading one as BGR uint8. One list
and one reader for every command that takes a folder of frames (`tacf track`, `eval`, `publish`, `demo`), so that
a folder one of them accepts, the others read alike."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")


def is_image(path: Path) -> bool:
    """An image file by its suffix; not a hidden one: a folder copied from a Mac to a FAT or exFAT drive holds
    `._000001.jpg` (AppleDouble metadata) beside each frame, which `tacf track` failed on after the last frame."""
    return not path.name.startswith(".") and path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES


def opencv_path(path: str | os.PathLike) -> bytes:
    """A file's path as OpenCV's file functions take it: the bytes of its name on disk. OpenCV's bindings encode a
    str as UTF-8 and crash the process (SIGSEGV) on one that cannot be, as Python decodes a name's bytes that are not
    UTF-8 (a folder unzipped from a Chinese Windows archive: GBK) or not of the locale to lone surrogates."""
    return os.fsencode(path)


def read_image(path: Path) -> np.ndarray | None:
    """An image file as BGR uint8 (None if unreadable). Deeper images (16-bit thermal frames, float TIFFs) are
    stretched from their own minimum to their maximum, as a thermal camera's automatic gain does; cutting them to
    their high byte would leave 12-bit data almost black."""
    import cv2

    if path.suffix.lower() in (".tif", ".tiff"):
        # as it is: a one-channel float TIFF (a radiometric thermal export) fails IMREAD_COLOR
        image = cv2.imread(opencv_path(path), cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim == 3 and image.shape[2] not in (3, 4):
            return None
        if image.dtype.kind == "f":
            # NaN (nothing measured) and -inf at the floor, +inf at the top: as the largest float, an inf pixel
            # stretched the rest of the image to black
            finite = image[np.isfinite(image)]
            low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
            image = np.nan_to_num(image, nan=low, posinf=high, neginf=low)
        # numpy's channels, not cvtColor's: that refused doubles and signed or 32-bit integers with a traceback
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        elif image.shape[2] == 4:
            image = np.ascontiguousarray(image[..., :3])
    else:
        image = cv2.imread(opencv_path(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    if image is None or image.dtype == np.uint8:
        return image
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX, cv2.CV_8U)
