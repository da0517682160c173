"""viser's wire protocol (1.1.x) as a client speaks it: the subprotocol, the camera message a page
opens with, a GUI update, server frames and the designer's readout.

Server frames: two little-endian u64 lengths, a zstd msgpack body (``messages``, ``timestampSec``
from the server's ``perf_counter``, the system's monotonic clock, ``binaryBufferLengths``) and
8-byte aligned buffers its ``{"__binary_index", "dtype"}`` placeholders point to.
"""

from __future__ import annotations

import re

import msgspec
import numpy as np
import zstandard

CAMERA = {
    "type": "ViewerCameraMessage",
    "wxyz": [1.0, 0.0, 0.0, 0.0],
    "position": [-2.5, -3.5, 2.5],
    "fov": 0.8727,
    "near": 0.01,
    "far": 1000.0,
    "image_height": 600,
    "image_width": 960,
    "look_at": [0.5, 0.0, 0.0],
    "up_direction": [0.0, 0.0, 1.0],
}
"""What a 960x600 page reports of its camera when it opens (the browser driver's viewport)."""
_SLIDERS = re.compile(r'data-sliders="([^"]*)"')
_STATE = re.compile(r'data-state="([^"]*)"')


def subprotocol() -> str:
    import viser

    return f"viser-v{viser.__version__}"


def decode_frame(data: bytes) -> tuple[float, list[dict]]:
    """A server frame -> (its server timestamp, its messages with binary placeholders replaced by
    flat numpy arrays)."""
    raw_len = int.from_bytes(data[0:8], "little")
    zlen = int.from_bytes(data[8:16], "little")
    body = msgspec.msgpack.decode(
        zstandard.ZstdDecompressor().decompress(data[16 : 16 + zlen], max_output_size=raw_len)
    )
    buffers, offset = [], 16 + zlen
    for n in body["binaryBufferLengths"]:
        offset += (-offset) % 8
        buffers.append(data[offset : offset + n])
        offset += n

    def resolve(obj):
        if isinstance(obj, dict):
            if "__binary_index" in obj and "dtype" in obj:
                return np.frombuffer(buffers[obj["__binary_index"]], dtype=np.dtype(obj["dtype"]))
            return {k: resolve(v) for k, v in obj.items()}
        if isinstance(obj, list):
            return [resolve(v) for v in obj]
        return obj

    return float(body["timestampSec"]), [resolve(m) for m in body["messages"]]


def gui_update(uuid: str, value) -> bytes:
    """A client frame: set a GUI control's value (a slider's, a checkbox's; True presses a button)."""
    return msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}})


def parse_readout(content: str) -> tuple[tuple[float, ...] | None, str | None]:
    """The slider values and replay state a readout's HTML is for (None where it has none)."""
    sliders, state = _SLIDERS.search(content), _STATE.search(content)
    values = tuple(float(v) for v in sliders.group(1).split(",")) if sliders and sliders.group(1) else None
    return values, state.group(1) if state else None
