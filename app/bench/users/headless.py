"""A minimal headless viser client: opens the websocket a browser tab would and reports a camera.

viser registers a client on its first camera message; this is enough for the server to build a
``DesignerClient`` whose GUI can then be driven from Python. Used by ``bench app`` and the
integration tests (the browser tests use real Chromium).
"""

from __future__ import annotations

import threading

import msgspec
import viser
from viser import _messages
from websockets.sync.client import connect


class HeadlessClient:
    """Connects to a viser server on localhost and drains everything it sends."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.ws = connect(
            f"ws://{host}:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
            open_timeout=10,
        )
        camera = _messages.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0),
            position=(-2.5, -3.5, 2.5),
            fov=1.0,
            near=0.01,
            far=1000.0,
            image_height=720,
            image_width=1280,
            look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 0.0, 1.0),
        )
        self.ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        self.bytes_received = 0
        self._thread = threading.Thread(target=self._drain, daemon=True, name="headless-viser-client")
        self._thread.start()

    def _drain(self) -> None:
        try:
            for message in self.ws:
                self.bytes_received += len(message)
        except Exception:  # closed by either side
            return

    def close(self) -> None:
        self.ws.close()
        self._thread.join(timeout=5)
