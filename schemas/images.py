"""Frame <-> image (numpy). Kept apart from the models so that importing tacf_schemas never loads OpenCV; here
OpenCV is loaded only to encode or decode pixels, so check_frame serves processes that never need it.

decode_frame accepts jpeg, png, bgr8 and mono8 and returns an HxWx3 BGR or HxW gray uint8 array. Encoded
images have their header read *before* decoding, so a frame whose real size differs from width/height, a
decompression bomb or a 16-bit PNG is rejected without allocating its pixels. Every failure is a FrameError with
a `code`.
"""
from __future__ import annotations

import struct
import time

import numpy as np

from .limits import MAX_FRAME_BYTES, MAX_FRAME_HEIGHT, MAX_FRAME_PIXELS, MAX_FRAME_WIDTH, MAX_JPEG_SCANS
from .models import ENCODINGS, Frame


class FrameError(ValueError):
    """A frame that cannot be turned into an image. code: unsupported_encoding, too_large, size_mismatch,
    corrupt."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


def check_dimensions(width: int, height: int) -> None:
    if width < 1 or height < 1:
        raise FrameError("size_mismatch", f"frame size {width}x{height} is empty")
    if width > MAX_FRAME_WIDTH or height > MAX_FRAME_HEIGHT or width * height > MAX_FRAME_PIXELS:
        raise FrameError("too_large", f"frame size {width}x{height} exceeds the limits "
                                      f"({MAX_FRAME_WIDTH}x{MAX_FRAME_HEIGHT}, {MAX_FRAME_PIXELS} pixels)")


def check_frame(frame: Frame) -> None:
    """Everything decode_frame checks before it decodes the pixels (encoding, sizes, the image's header), without
    OpenCV: FrameError if the frame cannot be an image of its stated size."""
    width, height, data = frame.width, frame.height, frame.data
    check_dimensions(width, height)
    if len(data) > MAX_FRAME_BYTES:
        raise FrameError("too_large", f"frame data of {len(data)} bytes exceeds {MAX_FRAME_BYTES}")
    if frame.encoding in ("bgr8", "mono8"):
        channels = 3 if frame.encoding == "bgr8" else 1
        if len(data) != height * width * channels:
            raise FrameError("size_mismatch", f"raw frame of {width}x{height}x{channels} needs "
                                              f"{height * width * channels} bytes, got {len(data)}")
        return
    if frame.encoding == "jpeg":
        header_size = jpeg_size(data)
    elif frame.encoding == "png":
        header_size = png_size(data)
    else:
        raise FrameError("unsupported_encoding", f"unsupported frame encoding {frame.encoding!r}; "
                                                 f"expected one of {', '.join(ENCODINGS)}")
    if header_size != (width, height):
        raise FrameError("size_mismatch", f"{frame.encoding} image is {header_size[0]}x{header_size[1]} but "
                                          f"the frame says {width}x{height}")
    # Each scan costs the decoder a pass over the whole image, whatever its bytes (and entropy-coded data holds no
    # 0xFFDA): 500 scans of 33 bytes made an 82 kB 4096x4096 frame take 7.9 s, and a 130 kB one held a worker until
    # its 15 s watchdog killed it.
    if frame.encoding == "jpeg" and (scans := data.count(b"\xff\xda")) > MAX_JPEG_SCANS:
        raise FrameError("unsupported_encoding", f"jpeg of {scans} scans; at most {MAX_JPEG_SCANS} are supported")
    if frame.encoding == "png" and len(data) > 24 and data[24] > 8:      # IHDR's bit depth
        # decode_frame refuses such pixels too, but only once OpenCV has decoded them all (a 130 kB PNG of 4096x4096
        # 16-bit RGBA: 1 s and 256 MB), and the service checks a start's frames with this function alone
        raise FrameError("unsupported_encoding", f"png with {data[24]}-bit samples; only 8-bit is supported")


def decode_frame(frame: Frame) -> np.ndarray:
    """The frame's pixels: HxWx3 BGR uint8 (jpeg, png, bgr8) or HxW uint8 (mono8, gray jpeg/png).

    Raw encodings return a read-only view of frame.data (no copy)."""
    check_frame(frame)
    if frame.encoding in ("bgr8", "mono8"):
        shape = (frame.height, frame.width) if frame.encoding == "mono8" else (frame.height, frame.width, 3)
        return np.frombuffer(frame.data, np.uint8).reshape(shape)
    import cv2

    image = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError("corrupt", f"corrupt {frame.encoding} data ({len(frame.data)} bytes)")
    return _normalise(image, frame.width, frame.height, frame.encoding)


def encode_frame(image: np.ndarray, seq: int, encoding: str = "jpeg", *, quality: int = 90,
                 stamp_ns: int | None = None) -> Frame:
    """A Frame of an HxWx3 BGR or HxW (HxWx1) gray uint8 image. bgr8 needs 3 channels, mono8 one. FrameError (too_large)
    for an image beyond the wire limits, which every service would refuse."""
    import cv2

    if (not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3)
            or image.ndim == 3 and image.shape[2] not in (1, 3)):     # not 2 or 4: OpenCV's error, or a BGRA PNG
        raise ValueError("image must be an HxW, HxWx1 or HxWx3 uint8 numpy array, got "
                         + (f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__))
    height, width = image.shape[:2]
    check_dimensions(width, height)
    channels = 1 if image.ndim == 2 else image.shape[2]
    if encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        data = buf.tobytes() if ok else None
    elif encoding == "png":
        ok, buf = cv2.imencode(".png", image)
        data = buf.tobytes() if ok else None
    elif encoding == "bgr8" and channels == 3:
        data = np.ascontiguousarray(image).tobytes()
    elif encoding == "mono8" and channels == 1:
        data = np.ascontiguousarray(image).tobytes()
    else:
        raise ValueError(f"cannot encode a {channels}-channel image as {encoding!r}")
    if data is None:
        raise ValueError(f"OpenCV failed to encode the image as {encoding}")
    if len(data) > MAX_FRAME_BYTES:
        raise FrameError("too_large", f"{encoding} frame data of {len(data)} bytes exceeds {MAX_FRAME_BYTES}")
    return Frame(seq=seq, stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns, encoding=encoding,
                 width=width, height=height, data=data)


def _normalise(image: np.ndarray, width: int, height: int, encoding: str) -> np.ndarray:
    import cv2

    if image.dtype != np.uint8:
        raise FrameError("unsupported_encoding", f"{encoding} with {image.dtype} pixels; only 8-bit is supported")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    elif image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] != 3:
        raise FrameError("unsupported_encoding", f"{encoding} with {image.shape[2]} channels")
    if image.shape[:2] != (height, width):
        raise FrameError("size_mismatch", f"decoded {encoding} is {image.shape[1]}x{image.shape[0]}, "
                                          f"the frame says {width}x{height}")
    return image


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk; FrameError if it is not a PNG."""
    if len(data) < 24 or data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        raise FrameError("corrupt", "not a PNG image (bad signature or missing IHDR)")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


# JPEG start-of-frame markers carry the image size; C4 (DHT), C8 (JPG) and CC (DAC) share the range but do not.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame segment; FrameError if there is none."""
    if len(data) < 4 or data[0] != 0xFF or data[1] != 0xD8:
        raise FrameError("corrupt", "not a JPEG image (no SOI marker)")
    pos, end = 2, len(data)
    while pos + 4 <= end:
        if data[pos] != 0xFF:
            raise FrameError("corrupt", f"corrupt JPEG: expected a marker at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:               # fill byte
            pos += 1
            continue
        if marker in (0x01,) or 0xD0 <= marker <= 0xD8:   # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
        if length < 2:
            raise FrameError("corrupt", "corrupt JPEG: segment length < 2")
        if marker in _SOF_MARKERS:
            if pos + 9 > end:
                break
            height, width = struct.unpack(">HH", data[pos + 5:pos + 9])
            return width, height
        if marker == 0xDA:               # start of scan before any SOF
            break
        pos += 2 + length
    raise FrameError("corrupt", "corrupt JPEG: no start-of-frame segment")
