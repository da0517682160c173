"""A server's decodes in a child process (``app.server.decode_process``): the same bits as a thread's, its
errors told, and a server that carries on when the child dies."""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pytest
import torch

from snakeloco.app.bench.users.load_driver import wait_until
from snakeloco.app.designer.session import Latents, decode_latents
from snakeloco.app.server.decode_process import IN_FLIGHT, DecodePool, DecodeProcess, decode_pids
from snakeloco.model.api import load_pretrained


def test_the_decode_process_decodes_the_same_bits_as_a_thread(checkpoint):
    models = [load_pretrained("structured"), load_pretrained(checkpoint)]  # projects onto members; does not
    process = DecodeProcess([m.path for m in models], torch.get_num_threads())
    try:
        assert process.pid in decode_pids()
        assert wait_until(lambda: process.ready, 120), process.failed
        for model in models:
            z = (
                model.sample_z_b(3, seed=11)
                if model.config.density
                else np.random.default_rng(1).normal(size=(3, model.z_b_dim))
            )
            for row, (mode, seed) in zip(z, (("zero", 0), ("sampled", 4), ("sampled", 5)), strict=True):
                latents = Latents(z_b=tuple(map(float, row)), zk_mode=mode, seed=seed)
                there, here = process.decode(model.path, latents), decode_latents(model, latents)
                for name in ("shape", "body_ds", "commands"):
                    assert np.array_equal(getattr(there, name), getattr(here, name)), name
                assert (there.member, there.residual, there.off_data, there.stats) == (
                    here.member,
                    here.residual,
                    here.off_data,
                    here.stats,
                )
                assert there.latents == latents
        assert models[0].projects and not models[1].projects
        assert process.served == 6
        # A decode that fails there is told here; a checkpoint it did not load is left to the caller.
        with pytest.raises(RuntimeError, match="decode process: ValueError: z_b must be"):
            process.decode(models[0].path, Latents(z_b=(0.0,)))
        assert process.decode(None, latents) is None and process.failed is None
    finally:
        process.close()
    assert process.pid not in decode_pids() and process.failed == "closed"
    assert process.decode(models[0].path, latents) is None


def test_requests_in_flight_together_each_get_their_own_reply(checkpoint):
    """``IN_FLIGHT`` requests share one child: the next waits in its socket while it decodes the
    first, and every caller reads the reply to its own request, in the order they were sent."""
    model = load_pretrained(checkpoint)
    pool = DecodePool([model.path], torch.get_num_threads(), processes=1)
    (process,) = pool.processes
    rows = np.random.default_rng(2).normal(size=(6, 4, model.z_b_dim))
    got: dict[tuple[int, int], object] = {}
    most = []

    def tab(i: int) -> None:
        for j, row in enumerate(rows[i]):
            latents = Latents(z_b=tuple(map(float, row)))
            with pool.turns:
                most.append((pool.turns.queued(), process.in_flight))
                got[i, j] = pool.decode(model.path, latents, lambda _: None)

    try:
        assert wait_until(lambda: process.ready, 120), process.failed
        threads = [threading.Thread(target=tab, args=(i,)) for i in range(len(rows))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert len(got) == rows.shape[0] * rows.shape[1] and process.served == len(got)
        for (i, j), decoded in got.items():
            assert decoded.latents.z_b == tuple(map(float, rows[i, j]))  # its own, not a neighbour's
        here = decode_latents(model, got[3, 2].latents)
        assert np.array_equal(got[3, 2].commands, here.commands)
        # a request went out while another's was in flight; more tabs than that waited their turn
        assert max(f for _, f in most) == IN_FLIGHT - 1 and max(q for q, _ in most) > IN_FLIGHT
        assert process.in_flight == 0 and process.failed is None
    finally:
        pool.close()
    assert process.failed == "closed"


def test_a_pool_without_processes_decodes_in_the_callers_thread_one_at_a_time():
    pool = DecodePool([], 0, processes=0)
    calls = []
    assert pool.decode("anywhere", "latents", lambda latents: calls.append(latents) or "decoded") == "decoded"
    assert calls == ["latents"] and pool.processes == [] and pool.turns.queued() == 0
    pool.close()


@pytest.mark.slow
def test_a_server_decodes_in_its_process_and_carries_on_when_it_dies(checkpoint):

    from helpers import apply, connect_headless, quiet_server

    srv = quiet_server(checkpoint)
    client = None
    try:
        (process,) = srv.decoding.processes
        client, d = connect_headless(srv)
        assert wait_until(lambda: process.ready, 120), process.failed
        served = process.served
        assert apply(d, d.sliders[0], 0.7, 60) and d.decoded.latents.z_b[0] == pytest.approx(0.7)
        assert process.served == served + 1 and srv.errors == []
        os.kill(process.pid, signal.SIGKILL)
        assert apply(d, d.sliders[0], -0.4, 60)  # decoded in the tab's own thread from now on
        assert d.decoded.latents.z_b[0] == pytest.approx(-0.4) and d.simulated is not None
        assert process.failed.startswith("decode process ended (exit code -9")
        assert len(srv.errors) == 1 and "decoding in the server's threads from now on" in srv.errors[0]
        assert apply(d, d.sliders[0], 0.2, 60) and len(srv.errors) == 1  # told once
    finally:
        if client is not None:
            client.close()
        srv.stop()
    assert decode_pids() == set()


def test_a_child_whose_server_left_while_it_started_leaves_quietly():
    import socket
    import subprocess
    import sys

    from snakeloco.model.checkpoint import SHIPPED

    ours, theirs = socket.socketpair()
    child = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "snakeloco.app.server.decode_process",
            str(theirs.fileno()),
            "1",
            str(SHIPPED["structured"]),
        ],
        pass_fds=(theirs.fileno(),),
        stderr=subprocess.PIPE,
        text=True,
    )
    theirs.close()
    ours.close()  # the server is gone before the child has loaded its checkpoints
    assert child.communicate(timeout=120)[1] == "" and child.returncode == 0


def test_a_member_decode_leaves_its_statistics_to_the_ensembles_score():
    """The designer's decode of an exact member skips the statistics head (a quarter of the decode a
    slider move waits for); the ensemble's score predicts them for the member as ``decode_members``
    does, to the bit."""
    from snakeloco.app.designer.session import GaitSession

    model = load_pretrained("structured")
    session = GaitSession(model, ensemble=2, workers=1)
    try:
        for row in model.sample_z_b(2, seed=11):
            gait = decode_latents(model, Latents(z_b=tuple(map(float, row))))
            stats = model.decode_members(row[None])[4]
            assert gait.stats is None and gait.member is not None
            assert session.decoded_stats(gait) == {k: float(v[0]) for k, v in stats.items()}
    finally:
        session.close()
