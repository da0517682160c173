"""``snakeloco bench screen``: the structured family's cheap screen against the full one and against
the family shipped before it, measured side by side; and how often the cheap verdict differs from
the full one on a sample of draws."""

from __future__ import annotations

import time

import numpy as np

from snakeloco.sim.data.chunks import _ensemble, draw_record, simulate_structured
from snakeloco.sim.data.generate_config import GenerateConfig
from snakeloco.sim.gaits.structured import DEFAULT_PRESET, STRUCTURED_PRESETS, StructuredConfig
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.scores.consistency import ensemble_spread

CHUNK = 8
"""Records per timed chunk; the screens take turns chunk by chunk, so the machine's load falls on
each alike."""


def _full(sc: StructuredConfig) -> StructuredConfig:
    """The same family screened in full: every draw's replays to 100 s, every member for a keeper."""
    return sc.model_copy(update={"early_seconds": 0.0, "sure_spread": 0.0})


def rates(records: int, seed: int, simulator: Simulator) -> dict:
    """Records per second, rejection rate and seconds of physics per record of the default family's
    screen, of the same family screened in full, and of the undulation family the previous structured
    checkpoint was trained on (that one on half the records: it is four times slower)."""
    every = STRUCTURED_PRESETS[DEFAULT_PRESET]
    screens = {"cheap": every, "full": _full(every), "undulate": STRUCTURED_PRESETS["undulate"]}
    tally = {name: {"s": 0.0, "records": 0, "draws": 0} for name in screens}
    for start in range(0, records, CHUNK):
        indices = np.arange(start, min(records, start + CHUNK))
        for name, sc in screens.items():
            if name == "undulate" and start >= records // 2:
                continue
            cfg = GenerateConfig(num_samples=records, seed=seed, family="structured", structured=sc)
            t0 = time.perf_counter()
            chunk = simulate_structured(cfg, simulator, indices)
            tally[name]["s"] += time.perf_counter() - t0
            tally[name]["records"] += len(indices)
            tally[name]["draws"] += chunk.log["draws"]
    out = {}
    for name, t in tally.items():
        out[name] = {
            "records": t["records"],
            "records_per_s": t["records"] / t["s"],
            "rejection_rate": 1.0 - t["records"] / t["draws"],
            "wall_s": t["s"],
        }
    return out


def agreement(draws: int, seed: int, simulator: Simulator) -> dict:
    """Replay ``draws`` draws (seed, i, 0) of the default family as full ensembles over 100 s, and
    read off each screen's verdict from the same replays (a paused replay is the prefix of the whole
    one, tested): the early check (2 replays at early_seconds), the 2-replay verdict at 100 s with its
    shortcut (sure_spread), and the full one (all members at 100 s)."""
    sc = STRUCTURED_PRESETS[DEFAULT_PRESET]
    cfg = GenerateConfig(num_samples=draws, seed=seed, family="structured", structured=sc)
    rate = cfg.excitation.sample_rate
    n_early = round(sc.early_seconds * rate)

    def spread(body: np.ndarray) -> float:
        return ensemble_spread(body, rate)["final_spread"]

    k = sc.screen_members
    full = np.zeros(draws, bool)
    cheap = np.zeros(draws, bool)
    early_rejects = np.zeros(draws, bool)
    kinds = []
    for start in range(0, draws, CHUNK):
        idx = range(start, min(draws, start + CHUNK))
        ensembles = []
        for i in idx:
            commands, _, drawn = draw_record(cfg, i, 0)
            kinds.append(drawn["kind"])
            ensembles.append(_ensemble(cfg, i, 0, commands))
        result = simulator.simulate(np.concatenate(ensembles))
        for n, i in enumerate(idx):
            rows = slice(n * sc.members, (n + 1) * sc.members)
            if any(f is not None for f in result.failures[rows]):
                continue  # broken: every screen rejects it
            body = result.body[rows]
            full[i] = sc.verdict(spread(body), sc.members) == "keep"
            early_rejects[i] = n_early > 0 and spread(body[:k, :n_early]) > sc.early_max_spread
            first = sc.verdict(spread(body[:k]), k)  # the cheap screen's verdict, as simulate_structured's
            cheap[i] = not early_rejects[i] and (first == "keep" or (first == "more" and full[i]))
    kinds_arr = np.array(kinds)
    return {
        "draws": draws,
        "early_seconds": sc.early_seconds,
        "full_kept": int(full.sum()),
        "cheap_kept": int(cheap.sum()),
        "disagree": int((cheap != full).sum()),
        "cheap_keeps_full_rejects": int((cheap & ~full).sum()),
        "cheap_rejects_full_keeps": int((~cheap & full).sum()),
        "early_rejects": int(early_rejects.sum()),
        "early_rejects_full_keeps": int((early_rejects & full).sum()),
        "kept_by_kind": {  # kind: [kept by the cheap screen, drawn]
            k: [int((cheap & (kinds_arr == k)).sum()), int((kinds_arr == k).sum())]
            for k in sorted(set(kinds))
        },
    }


def bench_screen(records: int = 32, seed: int = 5, draws: int = 64, workers: int | None = None) -> dict:
    """Both measurements on one simulator (``workers`` threads)."""
    simulator = Simulator(workers)
    try:
        r = {"workers": simulator.workers, "seed": seed, "rates": rates(records, seed, simulator)}
        c = r["rates"]
        r["ratio_full"] = c["cheap"]["records_per_s"] / c["full"]["records_per_s"]
        r["ratio_undulate"] = c["cheap"]["records_per_s"] / c["undulate"]["records_per_s"]
        r["agreement"] = agreement(draws, seed + 1000, simulator) if draws else None
        return r
    finally:
        simulator.close()
