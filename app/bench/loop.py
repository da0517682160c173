"""``snakeloco bench loop``: gaits played closed loop against open loop, over the same variations.

Sections, each measured side by side in one run (docs/closed-loop.md has the figures):

- ``library``: the library's undulation and sidewinding over the default set and ``sampled`` sampled
  variations, open loop (end from the nominal end) and closed loop (*arrive*: end from the path's end).
- ``sensing``: the same two over the default set with pose noise 2 cm / 2 deg at 10 Hz, heading drift
  1 deg/min and 50 ms pose latency, against perfect sensing.
- ``off_path``: each started 1 m off its path and 30 deg off its heading (the path moved): the distance
  along the path, in body lengths, after which it stays within 0.1 m.
- ``timing``: 12 closed-loop variation replays (*on time*, 100 s) against the open-loop batch of the
  same 12, best of ``repeats``.
- ``designer``: one client on ``snakeloco serve``'s designer: seconds from a library gait's request
  of its closed-loop fan (when its replay is drawn) to the fan drawn.
- ``sampler``: ``gaits`` gaits of the structured checkpoint's slider density that travel at least
  ``min_distance`` m: the share with a steering input, open- and closed-loop end errors over the default
  set. Written gait by gait to ``out`` (resumable: a rerun with the same file skips the gaits in it).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from snakeloco.sim.control.closed_loop import cut_and_turn, make_follower, nominal_reference, run_closed_loop
from snakeloco.sim.control.find import find_steering
from snakeloco.sim.gaits.library import PRESETS
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.variations import DEFAULT_SET, Variation, sampled_set
from snakeloco.sim.scores.closed_loop import closed_loop_robustness
from snakeloco.sim.scores.robustness import robustness

SENSING = {
    "pose_noise_m": 0.02,
    "pose_noise_deg": 2.0,
    "heading_drift_deg_per_min": 1.0,
    "pose_latency": 0.05,
}
"""The issue's sensing: noise 2 cm / 2 deg, drift 1 deg/min, 50 ms latency (and 10 Hz, set below)."""


def _stats(values) -> dict:
    v = np.asarray([x for x in values if x is not None], np.float64)
    if not v.size:
        return {"n": 0, "median": None, "max": None}
    return {"n": int(v.size), "median": float(np.median(v)), "max": float(v.max())}


def _library(sim: Simulator, sampled: int, log) -> dict:
    out = {}
    variations = [*DEFAULT_SET, *sampled_set(sampled)]
    for name in ("undulate", "sidewind"):
        commands = PRESETS[name].gait.commands(sim.robot)
        steering = find_steering(commands, sim)
        closed = closed_loop_robustness(commands, variations, sim, steering)
        opened = robustness(commands, variations, sim)
        rows = []
        for c, o in zip(closed["variations"], opened["variations"], strict=True):
            rows.append(
                {
                    "name": c["name"],
                    "open_rel": o["rel"],
                    "closed_rel": c["rel"],
                    "arrived": c["arrived"],
                    "arrival_s": c["arrival_s"],
                    "saturated": c["saturated"],
                    "failure": c["failure"] or o["failure"],
                }
            )
        arrived = [r for r in rows if r["arrived"]]
        out[name] = {
            "steering": steering.line(),
            "distance_m": closed["distance_m"],
            "rows": rows,
            "open": _stats(r["open_rel"] for r in rows),
            "closed_arrived": _stats(r["closed_rel"] for r in arrived),
            "within_3pct_of_arrived": sum(r["closed_rel"] <= 0.03 for r in arrived),
            "arrived": len(arrived),
            "runs": len(rows),
            "late": [r["name"] for r in rows if not r["arrived"] and r["failure"] is None],
        }
        log(f"library {name}: {steering.line()}; arrived {len(arrived)}/{len(rows)}")
    return out


def _sensing(sim: Simulator, log) -> dict:
    out = {}
    noisy = [
        Variation(
            name=f"{v.name} + sensing",
            scale=v.scale,
            add={**v.add, **SENSING},
            set={**v.set, "pose_rate": 10.0},
        )
        for v in DEFAULT_SET
    ]
    for name in ("undulate", "sidewind"):
        commands = PRESETS[name].gait.commands(sim.robot)
        steering = find_steering(commands, sim)
        reference = nominal_reference(commands, sim, steering.period)
        clean = closed_loop_robustness(commands, DEFAULT_SET, sim, steering, reference)
        dirty = closed_loop_robustness(commands, noisy, sim, steering, reference)
        c = [r["end_error_m"] for r in clean["variations"] if r["arrived"]]
        d = [r["end_error_m"] for r in dirty["variations"] if r["arrived"]]
        out[name] = {
            "clean_m": _stats(c),
            "noisy_m": _stats(d),
            "arrived_clean": len(c),
            "arrived_noisy": len(d),
            "ratio_median": _stats(d)["median"] / max(_stats(c)["median"], 1e-9) if c and d else None,
        }
        log(
            f"sensing {name}: median end error {out[name]['clean_m']['median']} -> {out[name]['noisy_m']['median']} m"
        )
    return out


def _off_path(sim: Simulator, log) -> dict:
    out = {}
    turn = math.radians(30.0)
    for name in ("undulate", "sidewind"):
        commands = PRESETS[name].gait.commands(sim.robot)
        steering = find_steering(commands, sim)
        reference = nominal_reference(commands, sim, steering.period)
        normal = np.array([-math.sin(turn), math.cos(turn)])  # 1 m to the path's left, turned 30 deg
        moved = cut_and_turn(reference, len(reference) - 1, reference[0], turn) + normal
        (run,) = run_closed_loop(sim, [make_follower(commands, moved, steering, sim, "arrive")])
        e = np.abs(run.cross_track)
        far = np.flatnonzero(~(e < 0.1))
        settled = int(far[-1]) + 1 if far.size else 0
        along = float(run.progress[settled]) if settled < len(e) else None
        out[name] = {
            "settled_along_m": along,
            "settled_body_lengths": None if along is None else along / sim.robot.body_length,
            "settled_s": None if settled >= len(e) else float(run.times[settled] - sim.config.lead_in / 20.0),
            "end_error_rel": float(
                np.linalg.norm(run.end - moved[-1]) / np.linalg.norm(moved[-1] - moved[0])
            ),
            "arrived": run.arrived,
        }
        log(f"off path {name}: within 0.1 m after {along} m")
    return out


def _timing(sim: Simulator, repeats: int, log) -> dict:
    commands = PRESETS["undulate"].gait.commands(sim.robot)
    steering = find_steering(commands, sim, check=False)
    reference = nominal_reference(commands, sim, steering.period)
    robots = [v.apply(sim.robot) for v in DEFAULT_SET]
    batch = np.broadcast_to(commands, (len(robots), *commands.shape))
    opened, closed = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sim.simulate(batch, robots=robots)
        opened.append(time.perf_counter() - t0)
        followers = [make_follower(commands, reference, steering, sim, "on_time") for _ in robots]
        t0 = time.perf_counter()
        run_closed_loop(sim, followers, robots)
        closed.append(time.perf_counter() - t0)
    out = {"open_s": min(opened), "closed_s": min(closed), "ratio": min(closed) / min(opened), "replays": 12}
    log(
        f"timing: 12 replays open {out['open_s']:.1f} s, closed {out['closed_s']:.1f} s, ratio {out['ratio']:.2f}"
    )
    return out


def _designer(checkpoint, gaits: tuple[str, ...], log) -> dict:
    """The designer's closed-loop fan with one client: seconds from a library gait's replay drawn to
    its fan drawn, with the Variations fan on too (as ``snakeloco serve`` runs)."""
    from snakeloco.app.bench.users.headless import HeadlessClient
    from snakeloco.app.bench.users.load_driver import wait_until
    from snakeloco.app.server.lifecycle import DesignerServer, freeze_started, tune_process

    tune_process()
    server = DesignerServer(port=0, checkpoint=checkpoint, verbose=False)
    freeze_started()
    client = HeadlessClient(server.port)
    out = {}
    try:
        wait_until(lambda: server.clients, 10)
        tab = next(iter(server.clients.values()))
        tab.wait_idle(120)
        tab.loop.done.wait(600)
        for name in gaits:
            version = tab.files.load_baseline(name)
            deadline = time.monotonic() + 900
            while (
                not (tab.loop.version == version and tab.loop.done.is_set()) and time.monotonic() < deadline
            ):
                time.sleep(0.2)
            if tab.loop.seconds is None or tab.loop.version != version:
                out[name] = {"seconds": None, "status": tab.controls.loop.status.content}
                continue
            replayed = tab.timings[-1].replayed
            out[name] = {
                "seconds": tab.loop.seconds,
                "after_replay_s": time.perf_counter() - replayed if tab.loop.seconds is not None else None,
                "status": tab.controls.loop.status.content.splitlines()[0],
            }
            log(f"designer {name}: closed-loop fan {tab.loop.seconds} s after its request")
    finally:
        client.close()
        server.stop()
    return out


def travelling_draws(model, sim: Simulator, gaits: int, seed: int, min_distance: float):
    """4 x ``gaits`` draws of ``model``'s slider density (``seed``), replayed at once: their members,
    commands and end distances (m), and the first ``gaits`` that travel ``min_distance``, in draw order."""
    shapes = model.decode_shape(model.sample_z_b(4 * gaits, seed=seed))
    members, _ = model.members.project(shapes)
    commands = model.commands(shapes)
    result = sim.simulate(commands)
    ends = np.hypot(result.body[:, -1, 1], result.body[:, -1, 2])
    ok = [i for i in range(len(commands)) if result.failures[i] is None and ends[i] >= min_distance]
    return members, commands, ends, ok[:gaits]


def _sampler(
    sim: Simulator, gaits: int, seed: int, min_distance: float, checkpoint, out: Path | None, log
) -> dict:
    from snakeloco.model import load_pretrained

    model = load_pretrained(checkpoint or "structured")
    done = json.loads(out.read_text())["rows"] if out is not None and out.exists() else []
    rows = list(done)
    members, commands, ends, travels = travelling_draws(model, sim, gaits, seed, min_distance)
    log(f"sampler: {len(travels)} of {4 * gaits} draws travel >= {min_distance} m (kept the first {gaits})")
    seen = {r["draw"] for r in rows}
    for index in travels:
        if index in seen:
            continue
        t0 = time.perf_counter()
        cmd = commands[index]
        opened = robustness(cmd, DEFAULT_SET, sim)
        steering = find_steering(cmd, sim)
        row: dict = {
            "draw": index,
            "kind": members[index].kind,
            "kept": True,
            "distance_m": float(ends[index]),
            "steering": steering.kind,
            "steering_line": steering.line(),
            "open": _stats(r["rel"] for r in opened["variations"]),
        }
        if steering.steers:
            closed = closed_loop_robustness(cmd, DEFAULT_SET, sim, steering)
            row["closed"] = _stats(r["rel"] for r in closed["variations"])
            row["arrived"] = sum(r["arrived"] for r in closed["variations"])
        row["seconds"] = time.perf_counter() - t0
        log(
            f"sampler {len(rows) + 1}/{len(travels)}: draw {index} {row['kind']} {row['distance_m']:.1f} m, "
            f"{row['steering_line']}, open median {row['open']['median']:.2f}"
            + (
                f", closed median {row['closed']['median']:.3f} worst {row['closed']['max']:.3f}"
                if "closed" in row
                else ""
            )
        )
        rows.append(row)
        if out is not None:
            out.write_text(json.dumps({"rows": rows}))
    kept = [r for r in rows if r["kept"]]
    steered = [r for r in kept if r["steering"] != "none"]
    return {
        "gaits": len(kept),
        "steered_share": len(steered) / max(len(kept), 1),
        "open_median_of_medians": _stats(r["open"]["median"] for r in kept)["median"],
        "open_median_of_worst": _stats(r["open"]["max"] for r in kept)["median"],
        "closed_median_of_medians": _stats(r["closed"]["median"] for r in steered)["median"],
        "closed_median_of_worst": _stats(r["closed"]["max"] for r in steered)["median"],
        "by_kind": {
            k: {"n": sum(r["kind"] == k for r in kept), "steered": sum(r["kind"] == k for r in steered)}
            for k in sorted({r["kind"] for r in kept})
        },
        "no_input": [
            f"draw {r['draw']} ({r['kind']}): {r['steering_line']}" for r in kept if r["steering"] == "none"
        ],
        "rows": rows,
    }


def bench_loop(
    gaits: int = 64,
    seed: int = 0,
    min_distance: float = 2.0,
    sampled: int = 16,
    repeats: int = 2,
    sections: tuple[str, ...] = ("library", "sensing", "off_path", "timing", "sampler", "designer"),
    checkpoint=None,
    workers: int | None = None,
    out: Path | None = None,
    log=print,
) -> dict:
    """Closed loop against open loop (module docstring); the figures of each section asked for."""
    sim = Simulator(workers=workers)
    result: dict = {"workers": sim.workers}
    t0 = time.perf_counter()
    try:
        if "library" in sections:
            result["library"] = _library(sim, sampled, log)
        if "sensing" in sections:
            result["sensing"] = _sensing(sim, log)
        if "off_path" in sections:
            result["off_path"] = _off_path(sim, log)
        if "timing" in sections:
            result["timing"] = _timing(sim, repeats, log)
        if "sampler" in sections:
            result["sampler"] = _sampler(sim, gaits, seed, min_distance, checkpoint, out, log)
        if "designer" in sections:
            result["designer"] = _designer(checkpoint, ("undulate", "sidewind"), log)
    finally:
        sim.close()
    result["seconds"] = time.perf_counter() - t0
    return result
