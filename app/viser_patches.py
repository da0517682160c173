"""Where the designer reaches into viser's internals, in one place. Written for viser 1.1.x (the
``viser>=1.0,<1.2`` pin); each patch checks that the internals it needs exist and otherwise leaves
viser alone, so a newer viser degrades to the unpatched behaviour instead of failing.
"""

from __future__ import annotations

from collections.abc import Callable

import viser

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
    from viser import _messages

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
