"""Designer users without a browser: viser's wire protocol from asyncio (``bench load --driver
protocol``), costing next to nothing beside the server they measure. Against viser 1.1.x it does
what a page does on the wire: joins with the subprotocol ``viser-v{version}`` and a
``ViewerCameraMessage`` (no client exists until one arrives) and keeps reading; keeps the GUI it is
sent (creation messages by uuid, ``GuiUpdateMessage`` merges) and finds controls by label; pauses
playback and turns light rendering on; drags as viser's slider does (a value every 50 ms and a
trailing one), then rests.

The frames' timestamps (``bench.wire``) split a latency into server time and delivery. A drag is
matched to what it caused by the readout (``app.designer.readout``), which carries its gait's slider values
and the replay's state. Imports only numpy and viser's own dependencies (msgspec, zstandard,
websockets).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

import msgspec
import numpy as np
import websockets

from snakeloco.app.bench.users.wire import CAMERA, decode_frame, gui_update, parse_readout, subprotocol

SEND_PERIOD_S = 0.05
"""How often viser's slider sends a dragged value (it throttles to 50 ms and sends a trailing one). A
drag's sends keep to its own 50 ms grid from its first, so that one stall of the shared event loop
does not bunch clients' sends for the rest of their drags (docs/load.md, "SEND_PERIOD_S")."""
DWELL_SPREAD = 0.5
"""A client's rests after its drags are uniform within +-50% of ``--dwell``, and it starts after a
rest drawn from 0 to ``--dwell``: exact rests kept every client's sends on one grid, unlike
independent users (docs/load.md, "DWELL_SPREAD")."""
DONE_STATES = ("done", "failed")
JUMPS = 8
"""Moves of a client of the ``jumps`` pattern (issue 59's own load client): z_B 1 jumps to a random
value, the client waits for that gait's replay, rests ``JUMP_REST_S`` and jumps again."""
JUMP_REST_S = (0.5, 1.5)
"""Its rest after each replay (s, uniform)."""
JOIN_GAP_S = (1.0, 4.0)
"""How long after the client before it a client of the ``jumps`` pattern joins (s, uniform): as
people open the page one after another, each tab's first load (replay, ensemble, variations) runs
while the tabs before it move, and each starts moving once it has sliders, not once its first
replay is in."""
HELD_JUMPS = (3, 6)
"""The ``held`` pattern's jumps (0-based) that send the value z_B 1 already holds."""
PATTERNS = ("drags", "jumps", "held")
"""How the protocol clients move the sliders: ``drags`` (a random slider dragged in 10-30 sends,
resting ``dwell``), ``jumps`` (``JUMPS``: one value a move, the next once its replay is in; a
newcomer's tab, playback running and full rendering) or ``held`` (the jumps, but jumps
``HELD_JUMPS`` send the value the slider holds, each timed as issue 59's client timed every move:
until the Consistency panel next says "· replay", or ``settle_s``; ``held_ms``). viser calls no
callback for a value that did not change, so such a move starts nothing, and the panel's next
"· replay" is the previous gait's ensemble or Variations fan finishing."""
MOVES = 3
"""Single moves each client makes after its drags, each once the last one's replay is done: the
bytes of one slider move (decoded view, streamed replay, ensemble)."""


@dataclass
class Drag:
    """One drag: its final values and when (client ``perf_counter``) each stage reached the client."""

    slider: int
    values: tuple[float, ...]
    sent: float  # the trailing value went out
    decoded: float = float("nan")
    first_motion: float = float("nan")
    replayed: float = float("nan")
    server: dict[str, float] = field(default_factory=dict)  # the same stages' frame timestamps

    def stage(self, state: str, now: float, stamp: float) -> None:
        for name, states in (
            ("decoded", ("simulating", "streaming", *DONE_STATES)),
            ("first_motion", ("streaming", *DONE_STATES)),
            ("replayed", DONE_STATES),
        ):
            if state in states and not np.isfinite(getattr(self, name)):
                setattr(self, name, now)
                self.server[name] = stamp


class ProtocolClient:
    """One designer user on the wire. ``run`` joins, prepares the page as the browser driver does,
    then ``drag_for``; everything received is read as it comes."""

    def __init__(self, url: str, seed: int, gaits_seed: int | None = None) -> None:
        self.url = url.replace("http://", "ws://")
        self.rng = np.random.default_rng(seed)  # when: the start and the rests
        # what: which slider goes where, in which steps; clients with one ``gaits_seed`` drag through
        # the same gaits in the same order, each at its own times (None: ``seed``).
        self.gaits = np.random.default_rng(seed if gaits_seed is None else gaits_seed)
        self.gui: dict[str, dict] = {}  # uuid -> {"type", "value", "props"}
        self.bytes = 0
        self.frames = 0
        self.drags: list[Drag] = []
        self.readout: tuple[tuple[float, ...] | None, str | None] = (None, None)
        self.values: list[float] = []  # the slider values this client sent last
        self.delivery_s: list[float] = []  # frame made on the server -> read here
        self.send_late_s: list[float] = []  # a drag's send after the one before, past the 50 ms
        self.held_s: list[float] = []  # ``held`` jumps: the send -> the panel's next "· replay"
        self._panel_replay_at = float("nan")  # when the Consistency panel last said "· replay"
        self._changed = asyncio.Event()
        self._ws = None
        self.reading = True  # False: stop reading (a client that hangs; ``bench load`` tests)

    # --- the GUI as sent ---------------------------------------------------------------------

    def find(self, label: str, kind: str | None = None) -> str:
        """The uuid of the control labelled ``label`` (of message type ``kind``)."""
        for uuid, g in self.gui.items():
            if g["props"].get("label") == label and (kind is None or g["type"] == kind):
                return uuid
        raise KeyError(f"no control labelled {label!r} among {len(self.gui)} received")

    def sliders(self) -> list[str]:
        found = []
        i = 1
        while True:
            try:
                found.append(self.find(f"z_B {i}", "GuiSliderMessage"))
            except KeyError:
                return found
            i += 1

    def plot(self, title: str) -> list[np.ndarray] | None:
        """The series of the uPlot titled ``title`` as last received."""
        for g in self.gui.values():
            if g["type"] == "GuiUplotMessage" and g["props"].get("title") == title:
                return [np.asarray(s) for s in g["props"].get("data") or []]
        return None

    def _apply(self, message: dict, now: float, stamp: float) -> None:
        kind = message["type"]
        if kind.startswith("Gui") and "uuid" in message and "props" in message:
            self.gui[message["uuid"]] = {
                "type": kind,
                "value": message.get("value"),
                "props": dict(message["props"]),
            }
        elif kind == "GuiUpdateMessage" and message["uuid"] in self.gui:
            g = self.gui[message["uuid"]]
            for k, v in message["updates"].items():
                if k == "value":
                    g["value"] = v
                else:
                    g["props"][k] = v
            markdown = message["updates"].get("_markdown")
            if isinstance(markdown, str) and "· replay" in markdown:
                self._panel_replay_at = now
            content = message["updates"].get("content")
            if isinstance(content, str) and 'id="snakeloco-readout"' in content:
                self.readout = parse_readout(content)
                values, state = self.readout
                if values is not None and state is not None:
                    for drag in self.drags[-2:]:  # a drag's views arrive before the next one's
                        if np.allclose(values, drag.values, atol=5e-5):
                            drag.stage(state, now, stamp)
        elif kind == "GuiRemoveMessage":
            self.gui.pop(message.get("uuid"), None)

    async def _read(self, ws) -> None:
        async for data in ws:
            now = time.perf_counter()
            self.bytes += len(data)
            self.frames += 1
            stamp, messages = decode_frame(data)
            self.delivery_s.append(now - stamp)
            for message in messages:
                self._apply(message, now, stamp)
            self._changed.set()
            while not self.reading:
                await asyncio.sleep(0.5)

    async def wait_for(self, predicate, timeout: float) -> bool:
        deadline = time.perf_counter() + timeout
        while not predicate():
            left = deadline - time.perf_counter()
            if left <= 0:
                return False
            self._changed.clear()
            try:
                await asyncio.wait_for(self._changed.wait(), min(left, 0.5))
            except TimeoutError:
                pass
        return True

    async def send(self, uuid: str, value) -> None:
        await self._ws.send(gui_update(uuid, value))

    # --- a user ------------------------------------------------------------------------------

    async def join(self, timeout: float = 90.0, prepare: bool = True, first_replay: bool = True) -> None:
        """Connect, report a camera, wait for the sliders and (``first_replay``) the first replay;
        ``prepare``: pause playback and turn light rendering on (as the browser driver does; a
        newcomer does neither)."""
        self._ws = await websockets.connect(self.url, subprotocols=[subprotocol()], max_size=None)
        self._reader = asyncio.ensure_future(self._read(self._ws))
        await self._ws.send(msgspec.msgpack.encode(CAMERA))
        if not await self.wait_for(
            lambda: len(self.sliders()) > 0 and (not first_replay or self.readout[1] in DONE_STATES), timeout
        ):
            raise RuntimeError(f"the designer at {self.url} sent no sliders and replay within {timeout:g} s")
        self.values = [float(self.gui[u]["value"]) for u in self.sliders()]
        if prepare:
            await self.send(self.find("Pause", "GuiButtonMessage"), True)
            await self.send(self.find("Light rendering", "GuiCheckboxMessage"), True)

    async def jump(self, settle_s: float = 60.0, held: bool = False) -> Drag | None:
        """z_B 1 to a new random value in one send (a click on its track), waiting until that gait's
        replay is in (or ``settle_s``), then resting ``JUMP_REST_S``. ``held``: send the value it
        holds and wait for the panel's next "· replay" (``PATTERNS``), into ``held_s``."""
        uuid = self.sliders()[0]
        if held:
            sent = time.perf_counter()
            self._panel_replay_at = float("nan")
            await self.send(uuid, self.values[0])
            came = await self.wait_for(lambda: np.isfinite(self._panel_replay_at), settle_s)
            self.held_s.append(self._panel_replay_at - sent if came else settle_s)
            await asyncio.sleep(float(self.rng.uniform(*JUMP_REST_S)))
            return None
        props = self.gui[uuid]["props"]
        lo, hi, step = float(props["min"]), float(props["max"]), float(props["step"])
        value = self.values[0]
        while value == self.values[0]:  # a move whose value equals the last changes nothing
            value = round(round(float(self.gaits.uniform(lo, hi)) / step) * step, 6)
        self.values[0] = value
        drag = Drag(0, tuple(self.values), time.perf_counter())
        self.drags.append(drag)
        await self.send(uuid, value)
        await self.wait_for(lambda: np.isfinite(drag.replayed), settle_s)
        await asyncio.sleep(float(self.rng.uniform(*JUMP_REST_S)))
        return drag

    async def jump_for(
        self, jumps: int, join_after: float = 0.0, held: tuple[int, ...] = (), held_wait: float = 60.0
    ) -> None:
        """Join ``join_after`` s from now (its first load not awaited), then jump ``jumps`` times
        (those in ``held`` to the value held, each waiting at most ``held_wait`` s)."""
        await asyncio.sleep(join_after)
        await self.join(prepare=False, first_replay=False)
        await asyncio.sleep(float(self.rng.uniform(*JUMP_REST_S)))
        for k in range(jumps):
            await (self.jump(held_wait, held=True) if k in held else self.jump())

    async def drag(self, dwell: float) -> Drag:
        """Drag one random slider to a random value in 10-30 sends 50 ms apart (the last one sent
        twice, as viser's trailing send), then rest ``dwell`` s on average (``DWELL_SPREAD``)."""
        uuids = self.sliders()
        i = int(self.gaits.integers(len(uuids)))
        props = self.gui[uuids[i]]["props"]
        lo, hi, step = float(props["min"]), float(props["max"]), float(props["step"])
        start, target = self.values[i], float(self.gaits.uniform(lo, hi))
        n = int(self.gaits.integers(10, 30))
        path = [
            round(round(min(max(start + (target - start) * k / n, lo), hi) / step) * step, 6)
            for k in range(1, n + 1)
        ]
        final = [*self.values[:i], path[-1], *self.values[i + 1 :]]
        drag, begin = None, time.perf_counter()
        for k, value in enumerate(path):
            self.values[i] = value
            now = time.perf_counter()
            if k:  # this loop's timer, late when this machine's cores are busy
                self.send_late_s.append(now - (begin + k * SEND_PERIOD_S))
            if drag is None and self.values == final:  # timed from the final value's first send
                drag = Drag(i, tuple(final), now)  # (its view can beat the last sends)
                self.drags.append(drag)
            await self.send(uuids[i], value)
            # the next send on this drag's grid (``SEND_PERIOD_S``), not 50 ms after this one
            await asyncio.sleep(max(0.0, begin + (k + 1) * SEND_PERIOD_S - time.perf_counter()))
        await self.send(uuids[i], self.values[i])  # viser's trailing send
        await asyncio.sleep(dwell * float(self.rng.uniform(1 - DWELL_SPREAD, 1 + DWELL_SPREAD)))
        return drag

    async def move(self, settle_s: float = 60.0, after_s: float = 0.5) -> int:
        """One slider to one new value (a click on the track), waiting for its replay and
        ``after_s`` more: the bytes that move cost this client (its decoded view, streamed replay,
        ensemble; playback is paused)."""
        uuids = self.sliders()
        i = int(self.gaits.integers(len(uuids)))
        props = self.gui[uuids[i]]["props"]
        value = round(float(self.gaits.uniform(props["min"], props["max"])) / props["step"]) * props["step"]
        self.values[i] = round(value, 6)
        before = self.bytes
        await self.send(uuids[i], self.values[i])

        def done() -> bool:
            values, state = self.readout
            return state in DONE_STATES and values is not None and np.allclose(values, self.values, atol=5e-5)

        await self.wait_for(done, settle_s)
        await asyncio.sleep(after_s)
        return self.bytes - before

    async def drag_for(self, seconds: float, dwell: float) -> None:
        end = time.perf_counter() + seconds
        await asyncio.sleep(float(self.rng.uniform(0.0, dwell)))  # users do not start together
        while time.perf_counter() < end:
            await self.drag(dwell)

    async def close(self) -> None:
        if self._ws is not None:
            await self._ws.close()
            self._reader.cancel()

    def summary(self) -> dict:
        """Per-drag figures (ms), bytes, and what the stream last said (for the stale checks)."""
        drags = self.drags

        def ms(stage: str) -> list[float]:
            return [1e3 * (getattr(d, stage) - d.sent) for d in drags if np.isfinite(getattr(d, stage))]

        def server_ms(stage: str) -> list[float]:
            return [1e3 * (d.server[stage] - d.sent) for d in drags if stage in d.server]

        plot = self.plot("forward (m)")
        return {
            "drags": len(drags),
            # When each drag's last value went out (client perf_counter): the long run's per-minute figures.
            "sent": [d.sent for d in drags],
            "stages_ms": [
                [1e3 * (getattr(d, k) - d.sent) for k in ("decoded", "first_motion", "replayed")]
                for d in drags
            ],
            "decoded_ms": ms("decoded"),
            "first_motion_ms": ms("first_motion"),
            "replay_ms": ms("replayed"),
            "decoded_server_ms": server_ms("decoded"),
            "replay_server_ms": server_ms("replayed"),
            "held_ms": [1e3 * t for t in self.held_s],
            "delivery_p95_ms": 1e3 * float(np.percentile(self.delivery_s, 95))
            if self.delivery_s
            else float("nan"),
            "send_late_p95_ms": 1e3 * float(np.percentile(self.send_late_s, 95))
            if self.send_late_s
            else float("nan"),
            "bytes": self.bytes,
            "frames": self.frames,
            "final_values": list(self.values),
            "readout_values": list(self.readout[0]) if self.readout[0] is not None else None,
            "readout_state": self.readout[1],
            "generated": plot[1].tolist() if plot and len(plot) > 1 else None,
            "simulated": plot[2].tolist() if plot and len(plot) > 2 else None,
        }


def stream_problems(s: dict) -> list[str]:
    """What a client's stream says is stale after its last drag settled: the readout for other
    slider values, or no replay state for them."""
    problems = []
    if s["readout_values"] is None or not np.allclose(s["readout_values"], s["final_values"], atol=5e-5):
        problems.append(
            f"the last readout is for sliders {s['readout_values']}, the client sent {s['final_values']}"
        )
    elif s["readout_state"] not in DONE_STATES:
        problems.append(
            f"the last readout for the final sliders says {s['readout_state']!r}, not done or failed"
        )
    if s["generated"] is None:
        problems.append("no generated path was received")
    return problems
