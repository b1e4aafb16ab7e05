"""Hard limits on wire payloads, shared by the codec, the image decoder and the service."""
from __future__ import annotations

SCHEMA_VERSION = 1

MAX_ID_LENGTH = 64
MAX_IMAGE_KEY_LENGTH = 256
MAX_IMAGE_KEY_CHUNKS = 16

MAX_FRAME_WIDTH = 8192
MAX_FRAME_HEIGHT = 8192
MAX_FRAME_PIXELS = 4096 * 4096          # 16.8 Mpx: a 4K UHD frame fits, a decompression bomb does not
# Scans of a JPEG frame: each makes the decoder go over the whole image again (a progressive JPEG has 6 to 10).
MAX_JPEG_SCANS = 64
MAX_FRAME_BYTES = 48 * 1024 * 1024      # covers raw 4096x4096 BGR (48 MiB); encoded frames are far smaller
MAX_PAYLOAD_BYTES = MAX_FRAME_BYTES + 64 * 1024   # a Frame's data plus its msgpack envelope

MAX_OVERRIDES = 64
MAX_CARRIED_FRAMES = 8                  # frames a start or reinit may carry (all within MAX_PAYLOAD_BYTES)
MAX_MESSAGE_LENGTH = 1024               # Error.message and similar free text
# msgpack objects in one payload (a SessionList of 600 sessions with 64 overrides each has about 117,000): msgpack's
# length limits hold per array, and an 8 MiB payload of empty arrays, a byte each, unpacked to 566 MiB
MAX_MSGPACK_OBJECTS = 1 << 17
