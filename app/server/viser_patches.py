"""Where the designer reaches into viser's internals, in one place. Written for viser 1.1.x (the
``viser>=1.0,<1.2`` pin); each patch checks that the internals it needs exist and otherwise leaves
viser alone, so a newer viser degrades to the unpatched behaviour instead of failing.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import viser
from viser import _messages

TARGET_VISER = "1.1"
"""The viser minor version these patches were written and tested against."""


def refuse_large_uploads(
    server: viser.ViserServer, max_bytes: int, refuse: Callable[[viser.ClientHandle, str, int], None]
) -> bool:
    """Refuse an upload larger than ``max_bytes`` when it starts, before any of it is buffered.

    viser (1.0-1.1) buffers a whole upload in memory before ``on_upload`` fires; its start message
    declares the size, so an oversized file is refused there (``refuse(client, filename, size)``
    tells the user) and its parts are then dropped unbuffered (viser ignores parts of a transfer it
    does not know). Returns whether the patch took; where it did not, callers still check the size
    in ``on_upload``.
    """
    gui = server.gui
    interface = getattr(gui, "_websock_interface", None)
    original = getattr(gui, "_handle_file_transfer_start", None)
    if interface is None or original is None or not hasattr(_messages, "FileTransferStartUpload"):
        return False

    def bounded(client_id, message) -> None:
        if message.size_bytes > max_bytes:
            client = server.get_clients().get(client_id)
            if client is not None:
                refuse(client, message.filename, message.size_bytes)
            return
        original(client_id, message)

    try:
        interface.unregister_handler(_messages.FileTransferStartUpload, original)
    except (AssertionError, ValueError):
        return False
    interface.register_handler(_messages.FileTransferStartUpload, bounded)
    return True


def share_prop_hints() -> bool:
    """Work out each scene node kind's property types once per kind, not once per node.

    viser (1.1) resolves ``typing.get_type_hints`` of a node's props class in a ``cached_property`` of
    each handle, so every node added pays it again on its first assignment: 0.75 ms of a decoded
    view's 3-4 ms of drawing (cProfile, one tab). The hints depend on the class alone; here they are
    kept per class and shared (viser only reads them). Returns whether the patch took."""
    from functools import cached_property
    from typing import get_type_hints

    try:
        from viser._assignable_props_api import AssignablePropsBase
    except ImportError:
        return False
    current = AssignablePropsBase.__dict__.get("_prop_hints")
    if not isinstance(current, cached_property):
        return False
    if getattr(current.func, "shared", False):
        return True
    by_class: dict[type, dict] = {}

    def hints(self) -> dict:
        kind = type(self._impl.props)
        found = by_class.get(kind)
        if found is None:
            found = by_class[kind] = get_type_hints(kind)
        return found

    hints.shared = True
    shared = cached_property(hints)
    shared.__set_name__(AssignablePropsBase, "_prop_hints")
    AssignablePropsBase._prop_hints = shared
    return True


def set_arrays(handle, **values: np.ndarray) -> None:
    """Assign several array properties of a scene node in one update message.

    viser sends one ``SceneNodeUpdateMessage`` per assigned property; a snake pose is two (link
    positions and orientations), 20 times a second per animating tab. Here the handle's stored
    props are updated as viser's own setter does (same dtype, a private copy for the wire) and one
    message carries both. Where the internals differ, each property is assigned the usual way.
    Nothing is queued once the connection has closed (its page left): viser would drop it and warn.
    """
    impl = getattr(handle, "_impl", None)
    api = getattr(impl, "api", None)
    props = getattr(impl, "props", None)
    if (
        api is None
        or props is None
        or not hasattr(api, "_queue_scene_message")
        or getattr(impl, "removed", False)
        or not all(isinstance(getattr(props, name, None), np.ndarray) for name in values)
    ):
        for name, value in values.items():
            setattr(handle, name, value)
        return
    updates = {}
    for name, value in values.items():
        current = getattr(props, name)
        value = np.asarray(value, dtype=current.dtype)
        if value.shape == current.shape:
            if np.array_equal(current, value):
                continue
            current[:] = value
        else:
            setattr(props, name, value.copy())
        updates[name] = value.copy()
    if updates and not _closed(getattr(api, "_websock_interface", None)):  # else never delivered
        api._queue_scene_message(_messages.SceneNodeUpdateMessage(impl.name, updates))


def set_plot_data(handle, data: tuple[np.ndarray, ...]) -> None:
    """Replace a uPlot's series with ``data`` in the arrays' own dtype (float32 here). viser casts
    a plot's data to float64 whatever it is given; uPlot draws typed arrays of any float width, and
    the page's decoder makes a Float32Array of a ``<f4`` buffer, so float32 halves every plot update
    (the plots were half of a slider move's bytes). Where the internals differ, viser's setter runs."""
    impl = getattr(handle, "_impl", None)
    props = getattr(impl, "props", None)
    if props is None or not hasattr(handle, "_queue_update") or getattr(impl, "removed", False):
        handle.data = data
        return
    props.data = data
    handle._queue_update("data", data)


def connection_closed(client: viser.ClientHandle) -> bool:
    """Whether ``client``'s connection has closed (its page left): what is queued for it now is never
    delivered, and viser warns of it. viser calls its disconnect callbacks a moment later; until
    then a tab's threads may still draw. False where the internals differ."""
    return _closed(getattr(client, "_websock_connection", None))


def _closed(connection) -> bool:
    """Whether a viser connection (a client's, or the server's) has closed its message buffer."""
    buffer = getattr(connection, "get_message_buffer", None)
    return bool(buffer is not None and getattr(buffer(), "done", False))


def run_javascript(client: viser.ClientHandle, source: str) -> bool:
    """Run ``source`` once in ``client``'s page (viser's own message for plotly's set-up); whether
    it was sent."""
    connection = getattr(client, "_websock_connection", None)
    message = getattr(_messages, "RunJavascriptMessage", None)
    if connection is None or message is None or not hasattr(connection, "queue_message"):
        return False
    connection.queue_message(message(source=source))
    return True
