"""The most robust members found, per kind and direction: ``snakeloco gait --search-robust``.

Candidates are the sampler's members a physics head was trained and scored on (``model.heads.physics_fit``):
each was replayed on the nominal robot and on every variation of the default set, so its worst case
is known without replaying. Only members the library can hold are considered (one gait-equation
wave: no steering, no curving wave). Each is put in a sector by where its nominal replay went
(forward, left, backward, right of its start heading; a turning gait by the way it turns) and, where
it travels at least ``MIN_TRAVEL`` m (turning gaits: any), ranked by its worst relative end change
over the set, read from the replays at the model's 5 Hz. The ``top`` of each sector are then
confirmed as the library measures its gaits: ``sim.gaits.library.measure_gait`` (a 4-member ensemble) and
``sim.scores.robustness.robustness`` at 20 Hz; the first whose ensemble spread is at most ``MAX_SPREAD``
and whose confirmed worst case is the smallest is the sector's gait; the library (``sim.gaits.library``)
takes it where that worst case is below the library's first gait of its kind (``beats_library``).

``robustness_by_kind`` is the same question for gaits the model generates (``evaluate
--robustness``): how far the default set moves their ends, per kind, against the noise floor.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from snakeloco.sim.robot.variations import DEFAULT_SET
from snakeloco.sim.scores.robustness import relative_change

if TYPE_CHECKING:
    from snakeloco.model.api import GaitModel

MIN_TRAVEL = 2.0
"""Metres a candidate must travel in 100 s to stand for its direction (turning gaits excepted)."""
MAX_SPREAD = 0.1
"""The library's own bar: where 0.1%-noisy replays end, over the distance (``sim.gaits.library``)."""
SECTORS = ("forward", "left", "backward", "right")


def sector(forward: float, sideways: float, net_yaw: float, kind: str) -> str:
    """Where a replay went: the quarter of its start frame it ended in (turning gaits: the way they turn)."""
    if kind == "turn":
        return "clockwise" if net_yaw < 0 else "counter-clockwise"
    heading = np.degrees(np.arctan2(sideways, forward))
    return SECTORS[int(((heading + 45.0) % 360.0) // 90.0)]


DRAWS = ("train", "eval")
"""The physics head's two draws of members: the ones it was trained on, the ones it was scored on."""


def candidates(
    checkpoint: str | Path | None, folder: str | Path | None = None, draws: tuple[str, ...] = DRAWS
) -> list[dict]:
    """Every member of ``draws`` with its nominal and default-set replays in the physics head's
    replay folder (default: the checkpoint's ``physics-gaits``): kind, member, sector, distance (m)
    and worst relative end change (5 Hz), the library-ready ones (``pure``) marked."""
    from snakeloco.model.api import load_pretrained
    from snakeloco.model.checkpoint import resolve_checkpoint
    from snakeloco.model.heads.physics_fit import PHYSICS_GAITS, replay_members_on_physics
    from snakeloco.model.heads.sampler import ZK_TEMPERATURE
    from snakeloco.model.options import PhysicsHeadConfig

    model = load_pretrained(checkpoint)
    if model.physics_head is None:
        raise ValueError(
            f"checkpoint {model.path}: no physics head, so no members replayed on the variations "
            "(snakeloco calibrate --physics-head fits one and keeps its replays)"
        )
    cfg = PhysicsHeadConfig(**model.physics_head.cfg.summary["config"])
    folder = Path(folder) if folder is not None else resolve_checkpoint(checkpoint) / PHYSICS_GAITS
    plan = [
        (model.sample_z_b(cfg.samples, cfg.seed), (None, ZK_TEMPERATURE), cfg.sampled, "train", False),
        (model.sample_z_b(cfg.eval_samples, cfg.eval_seed), (None,), 0, "eval", True),
    ]
    names = [v.name for v in DEFAULT_SET]
    out = []
    for z, modes, sampled, label, noise in plan:
        if not len(z) or label not in draws:
            continue
        r = replay_members_on_physics(model, z, modes, cfg, sampled, folder, None, label, noise, replay=False)
        for i in np.unique(r["member"]).astype(int):
            mine = np.flatnonzero(r["member"] == i)
            ends = {
                str(r["variation"][k]): r["body"][k, -1, 1:3] - r["body"][k, 0, 1:3] if r["ok"][k] else None
                for k in mine
            }
            home = ends.get("nominal")
            if home is None or any(n not in ends for n in names):
                continue
            rel = [np.inf if ends[n] is None else float(relative_change(ends[n], home)) for n in names]
            member = r["members"][i]
            nominal = mine[list(r["variation"][mine]).index("nominal")]
            net_yaw = float(r["body"][nominal, -1, 5] - r["body"][nominal, 0, 5])
            out.append(
                {
                    "draw": label,
                    "member": member,
                    "kind": member.kind,
                    "pure": member.curve is None and member.steering_amplitude == 0.0,
                    "sector": sector(*home, net_yaw, member.kind),
                    "distance_m": float(np.hypot(*home)),
                    "worst_rel": max(rel),
                    "worst": names[int(np.argmax(rel))],
                }
            )
    return out


def search_robust(
    checkpoint=None,
    folder=None,
    top: int = 3,
    workers: int | None = None,
    log=print,
    draws: tuple[str, ...] = DRAWS,
) -> dict:
    """The most robust library-ready member per kind and sector (module docstring): per sector the
    chosen gait's equation, measured figures and confirmed worst case, with how many candidates it
    was chosen from and the library's gait of its kind for comparison."""
    from snakeloco.sim.gaits.library import PRESETS, measure_gait
    from snakeloco.sim.physics.results import SimulationError
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.scores.robustness import robustness

    log = log or (lambda line: None)
    found = candidates(checkpoint, folder, draws)
    pool = [c for c in found if c["pure"] and (c["kind"] == "turn" or c["distance_m"] >= MIN_TRAVEL)]
    log(f"{len(found)} members replayed on the default set, {len(pool)} library-ready that travel")
    simulator = Simulator(workers)
    chosen = {}
    try:
        for key in sorted({(c["kind"], c["sector"]) for c in pool}):
            ranked = sorted(
                (c for c in pool if (c["kind"], c["sector"]) == key), key=lambda c: c["worst_rel"]
            )
            confirmed = []
            for c in ranked[:top]:
                gait = c["member"].wave
                try:
                    figures = measure_gait(gait, simulator)
                except SimulationError:
                    continue
                report = robustness(gait.commands(simulator.robot), DEFAULT_SET, simulator)
                if figures.spread <= MAX_SPREAD and report["worst_rel"] is not None:
                    confirmed.append((report["worst_rel"], c, figures, report))
            if not confirmed:
                log(f"{key[0]} {key[1]}: none of {len(ranked[:top])} confirmed (spread or a broken replay)")
                continue
            worst_rel, c, figures, report = min(confirmed, key=lambda x: x[0])
            library = PRESETS[c["kind"]].worst.rel if c["kind"] in PRESETS else None
            chosen[f"robust-{c['kind']}-{key[1]}"] = {
                "kind": c["kind"],
                "sector": key[1],
                "gait": c["member"].wave.model_dump(),
                "describe": c["member"].describe(),
                "measured": figures.model_dump(),
                "worst": {
                    "end_error_m": report["worst_end_error_m"],
                    "rel": worst_rel,
                    "variation": report["worst"],
                },
                "worst_rel_5hz": c["worst_rel"],
                "candidates": len(ranked),
                "library_worst_rel": library,
                # The library takes it only where it moves less than the library's gait of its kind.
                "beats_library": library is None or worst_rel < library,
            }
            log(
                f"{key[0]} {key[1]}: worst {100 * worst_rel:.0f}% ({report['worst']}) of "
                f"{figures.displacement:.1f} m, from {len(ranked)} candidates"
            )
    finally:
        simulator.close()
    return {"candidates": len(found), "draws": list(draws), "library_ready": len(pool), "chosen": chosen}


def write_library(found: dict, path: str | Path | None = None) -> list[str]:
    """Put the chosen gaits that beat the library's gait of their kind (``search_robust``'s result)
    into the library file (default ``sim.gaits.library.LIBRARY_FILE``), replacing the robust ones it held;
    the names written."""
    import json

    from snakeloco.sim.gaits.library import LIBRARY_FILE, GaitPreset

    path = Path(path) if path is not None else LIBRARY_FILE
    kept = [e for e in json.loads(path.read_text()) if not e["name"].startswith("robust-")]
    added = []
    for name, c in found["chosen"].items():
        if not c["beats_library"]:
            continue
        preset = GaitPreset(
            gait=c["gait"],
            about=f"{c['describe']}; {_where(c['sector'])}: the most robust of {c['candidates']} such "
            "members over the default variation set",
            measured=_figures(c["measured"]),
            worst=_figures(c["worst"]),
        )
        kept.append({"name": name, **preset.model_dump()})
        added.append(name)
    path.write_text(json.dumps(kept, indent=1) + "\n")
    return added


def _figures(values: dict) -> dict:
    """Measured figures to 4 significant digits, as the library keeps them (a replay on another CPU
    differs by more)."""
    return {k: float(f"{v:.4g}") if isinstance(v, float) else v for k, v in values.items()}


def _where(sector: str) -> str:
    if sector in ("clockwise", "counter-clockwise"):
        return f"turns {sector}"
    return {"forward": "ends ahead of its start", "backward": "ends behind its start"}.get(
        sector, f"ends {sector} of its start"
    )


def robustness_by_kind(
    model: GaitModel,
    shapes: np.ndarray,
    kinds: list[str],
    ensembles: np.ndarray,
    ok: np.ndarray,
    runner,
    per_job: int = 8,
) -> dict:
    """How far the default variation set moves generated gaits' end points, per kind, against the
    noise floor: gaits of ``shapes`` (n, J, L, 2) whose ensembles (n, K, 500, 6) ran already
    (member 0 the nominal replay, member 1 the first noisy copy: the floor) are replayed on every
    variation (``per_job`` gaits a backend job); ``sim.scores.robustness.change_table`` of the ends."""
    from snakeloco.model.heads.physics_fit import NOISE as floor
    from snakeloco.model.heads.physics_fit import simulate_rows
    from snakeloco.sim.scores.robustness import change_table

    n, v = len(shapes), len(DEFAULT_SET)

    def end(body: np.ndarray) -> np.ndarray:
        return body[..., -1, 1:3] - body[..., 0, 1:3]

    ends = {"nominal": np.where(ok[:, :1], end(ensembles[:, 0]), np.nan)}
    if ensembles.shape[1] > 1:
        ends[floor] = np.where(ok[:, 1:2], end(ensembles[:, 1]), np.nan)
    varied = np.full((n, v, 2), np.nan)
    starts = list(range(0, n, per_job))
    jobs = (
        (
            np.repeat(model.commands(shapes[s : s + per_job]), v, axis=0),
            list(DEFAULT_SET) * len(shapes[s : s + per_job]),
        )
        for s in starts
    )
    for b, (body, failures) in runner.map(simulate_rows, jobs):
        rows = slice(starts[b], starts[b] + len(failures) // v)
        ran = np.array([f is None for f in failures]).reshape(-1, v)
        varied[rows] = np.where(ran[..., None], end(body.astype(np.float64)).reshape(-1, v, 2), np.nan)
    ends |= {var.name: varied[:, k] for k, var in enumerate(DEFAULT_SET)}
    return change_table(kinds, ends, floor=floor if floor in ends else None)
