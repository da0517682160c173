"""The protocol clients' process (``bench load --driver protocol``): join the clients, let them move
the sliders (``ProtocolClient``: drags or jumps), report what each saw, and wait to be let go."""

from __future__ import annotations

import asyncio
import os
import time

import numpy as np

from snakeloco.app.bench.users.protocol import (
    DONE_STATES,
    HELD_JUMPS,
    JOIN_GAP_S,
    JUMPS,
    MOVES,
    ProtocolClient,
)


async def _run(
    url: str,
    seeds: list[int],
    seconds: float,
    dwell: float,
    settle_s: float,
    done=None,
    gaits_seed=None,
    pattern: str = "drags",
    held_wait: float = 60.0,
) -> dict:
    """Join ``len(seeds)`` clients, drag for ``seconds``, wait for each last drag's replay; returns the
    clients' summaries and the cores this process used while they dragged. ``gaits_seed``: every
    client drags through the gaits this seed draws (``ProtocolClient``), at times of its own seed.
    ``done``: a coroutine function awaited, clients still connected and reading, before they leave
    (the caller checks the server's tabs meanwhile)."""
    clients = [ProtocolClient(url, seed, gaits_seed) for seed in seeds]
    cpu0, wall0 = time.process_time(), time.perf_counter()
    if pattern in ("jumps", "held"):  # one after another, each moving once it has sliders (``JOIN_GAP_S``)
        gaps = np.cumsum([0.0, *(c.rng.uniform(*JOIN_GAP_S) for c in clients[1:])])
        held = HELD_JUMPS if pattern == "held" else ()
        bytes_before = [0] * len(clients)
        await asyncio.gather(
            *(c.jump_for(JUMPS, float(g), held, held_wait) for c, g in zip(clients, gaps, strict=True))
        )
    else:
        await asyncio.gather(*(c.join() for c in clients))
        bytes_before = [c.bytes for c in clients]
        cpu0, wall0 = time.process_time(), time.perf_counter()
        await asyncio.gather(*(c.drag_for(seconds, dwell) for c in clients))
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    moved = [c.bytes - b for c, b in zip(clients, bytes_before, strict=True)]

    def settled(c: ProtocolClient) -> bool:
        values, state = c.readout
        return state in DONE_STATES and values is not None and np.allclose(values, c.values, atol=5e-5)

    await asyncio.gather(*(c.wait_for(lambda c=c: settled(c), settle_s) for c in clients))

    async def moves(c: ProtocolClient) -> list[int]:
        return [await c.move(settle_s) for _ in range(MOVES)]

    per_move = await asyncio.gather(*(moves(c) for c in clients))
    result = {
        "clients": [
            c.summary() | {"bytes_dragging": m, "bytes_per_move": b}
            for c, m, b in zip(clients, moved, per_move, strict=True)
        ],
        "driver_cores": cpu / wall if wall > 0 else float("nan"),
        "wall_s": wall,
    }
    if done is not None:
        await done(result)
    for c in clients:
        await c.close()
    return result


def main(
    conn,
    url: str,
    seeds: list[int],
    seconds: float,
    dwell: float,
    nice: int,
    settle_s: float,
    gaits_seed=None,
    pattern: str = "drags",
    held_wait: float = 60.0,
) -> None:
    """Process entry (``bench load``): run the clients (``_run``), send ``("ok", result)`` (or ``("error",
    message)``), and keep them connected until the benchmark sends anything back."""
    import traceback

    if nice and hasattr(os, "nice"):
        os.nice(nice)

    async def done(result: dict) -> None:
        conn.send(("ok", result))
        await asyncio.get_running_loop().run_in_executor(None, conn.poll, 600.0)

    try:
        asyncio.run(_run(url, seeds, seconds, dwell, settle_s, done, gaits_seed, pattern, held_wait))
    except Exception as exc:
        conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=4)}"))
    finally:
        conn.close()
