"""Small things several test files share (``tests/`` is on the test path: pyproject's pythonpath)."""

from __future__ import annotations

import contextlib
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from snakeloco.app.bench.users.headless import HeadlessClient
from snakeloco.app.bench.users.load_driver import CHROMIUM
from snakeloco.model import HierarchicalVAE, ModelConfig
from snakeloco.model.checkpoint import Normalization
from snakeloco.model.vae.config import TINY
from snakeloco.model.vae.train import init_signal_source
from snakeloco.sim.gaits.excitation import RECORD

SMALL = TINY
"""A network small enough to train in seconds on the 4-record test dataset."""


def random_commands(n: int, seed: int = 0) -> np.ndarray:
    """n random-phase multisine command records (n, T, 8) of the record's excitation (the paper
    family's gaits)."""
    from snakeloco.sim import multisine, random_phases

    rng = np.random.default_rng(seed)
    return np.stack([multisine(random_phases(rng, RECORD, 8), RECORD)[0] for _ in range(n)])


def free_port() -> int:
    """A TCP port nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


BROWSER = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.skipif(
        not Path(CHROMIUM).exists() and not shutil.which("chromium"),
        reason="Debian chromium not installed (CI installs it: apt-get install chromium)",
    ),
]
"""Marks of a test that drives real Chromium pages: slow, and skipped with the reason where Debian's
chromium is missing."""


def connect_headless(srv, timeout: float = 60.0):
    """Open a headless viser client on a ``DesignerServer`` and wait (up to ``timeout`` s) for its tab to
    settle; returns the client (close it) and the tab's ``DesignerClient``."""
    before = set(srv.clients)
    client = HeadlessClient(srv.port)
    for _ in range(200):
        new = set(srv.clients) - before
        if new:
            designer = srv.clients[new.pop()]
            assert designer.wait_idle(timeout)
            return client, designer
        time.sleep(0.05)
    raise AssertionError("the server never registered the client")


def apply(d, control, value, timeout: float = 60.0) -> bool:
    """Set a GUI control of tab ``d`` as a user would and wait, on the tab's request version and not
    a clock, until the request it caused is the tab's newest and every job of it finished. False if
    no request came or it did not finish within ``timeout`` s each (viser runs the control's
    callback on its thread pool: on a starved machine that alone took over 10 s)."""
    from snakeloco.app.bench.users.load_driver import wait_until

    before = d.version
    control.value = value
    return wait_until(lambda: d.version > before, timeout) and d.wait_idle(timeout)


def unit_normalization() -> Normalization:
    """Zero means and unit stds: normalised values equal physical ones."""
    return Normalization(
        shape_mean=np.zeros((8, 2)).tolist(),
        shape_std=np.ones((8, 2)).tolist(),
        body_mean=[0.0] * 6,
        body_std=[1.0] * 6,
        stats_mean=[0.0] * 4,
        stats_std=[1.0] * 4,
    )


def fresh_net(cfg: ModelConfig = SMALL) -> HierarchicalVAE:
    """A fresh network whose signal branch uses the standard excitation and unit normalisation."""
    net = HierarchicalVAE(cfg)
    init_signal_source(net, RECORD.freqs, unit_normalization())
    return net


@contextlib.contextmanager
def designer_page(checkpoint, viewport: dict | None = None, server: dict | None = None, **page_options):
    """A designer server (ensemble 2; ``server``: other ``quiet_server`` options) and one Chromium page
    on it whose tab has settled: yields the Playwright module, the server, the page and the tab's
    ``DesignerClient``; all closed after."""
    from snakeloco.app.bench.users.load_driver import CHROMIUM_ARGS, wait_until

    sync_api = pytest.importorskip("playwright.sync_api")
    srv = quiet_server(checkpoint, **(server or {}))
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport=viewport or {"width": 1400, "height": 900}, **page_options)
                page.goto(f"http://127.0.0.1:{srv.port}")
                assert wait_until(lambda: len(srv.clients) == 1), "the page never connected"
                d = next(iter(srv.clients.values()))
                assert d.wait_idle(90)
                yield sync_api, srv, page, d
            finally:
                browser.close()
    finally:
        srv.stop()


def quiet_server(checkpoint=None, **overrides):
    """A designer server for a test: a free port, 2 physics threads, an ensemble of 2, no log, and no
    variation or closed-loop replays unless ``overrides`` ask (any ``DesignerServer`` option)."""
    from snakeloco.app.server.lifecycle import DesignerServer

    options = {
        "port": 0,
        "ensemble": 2,
        "workers": 2,
        "verbose": False,
        "variations": False,
        "closed_loop": False,
    }
    return DesignerServer(checkpoint=checkpoint, **(options | overrides))
