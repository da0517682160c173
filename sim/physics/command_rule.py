"""The command rule: how 20 Hz joint commands become servo targets, and when a rollout is broken.

Used identically by data generation, ``replay`` and CSV import (numpy only; ``sim.physics.simulator`` runs it):

1. Commands are 20 Hz samples u[n], n = 0..T-1, treated as one period of a periodic gait.
2. Lead-in: before the record the snake, lying straight and at rest, runs the last ``lead_in``
   samples of the gait (its periodic continuation), faded in by a raised-cosine ramp over the first
   ``ramp`` of them; this lets the servos and the body settle before t = 0. Nothing of the lead-in is
   measured.
3. Between samples the servo target is linearly interpolated from u[n] to u[n+1] (u[T] = u[0]),
   updated every physics step (2.5 ms, 20 steps per sample).
3a. A robot with command latency (``Robot.latency``) gets each step's target that many whole
   physics steps late; before the first target arrives the servos hold the rest pose (0 rad).
4. Measurements at record sample n are taken at t_n = n / 20 s, at the start of the interval whose
   target starts at u[n].
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class CommandRule(BaseModel):
    """How commands are applied and when a simulation counts as broken."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    lead_in: int = Field(60, ge=0, description="Lead-in samples before the record (3 s at 20 Hz).")
    ramp: int = Field(40, ge=1, description="Raised-cosine fade-in over this many lead-in samples.")
    max_com_height: float = Field(
        1.0,
        gt=0,
        description="Centre-of-mass height (m) above which the snake counts as thrown. A 0.9 m snake "
        "standing on its end has it at 0.48 m; healthy 100 s runs peaked at 0.58 m (128 samples).",
    )
    max_com_speed: float = Field(
        10.0,
        gt=0,
        description="Centre-of-mass speed (m/s) above which the run counts as diverged; healthy runs "
        "peaked at 3.0 m/s (128 samples).",
    )


def lead_in_window(cfg: CommandRule) -> np.ndarray:
    """Fade-in weights of the lead-in samples, shape (lead_in,), from 0 up to 1."""
    j = np.arange(cfg.lead_in)
    return np.where(j < cfg.ramp, 0.5 - 0.5 * np.cos(np.pi * j / cfg.ramp), 1.0)


def expand_commands(
    commands: np.ndarray,
    substeps: int,
    cfg: CommandRule,
    steps: tuple[int, int] | None = None,
    delay: int = 0,
) -> np.ndarray:
    """Per-physics-step servo targets for a batch of records (the command rule above).

    Args:
        commands: (B, T, J) rad.
        substeps: physics steps per command sample.
        cfg: lead-in settings.
        steps: only physics steps [begin, end) (a chunk of a streamed or resumed rollout): the same
            values as those of the whole expansion, without computing the rest (a replay superseded
            after its first chunk expanded 2000 samples for 80).
        delay: command latency in physics steps: step s gets the target of step s - delay (the rest
            pose, 0 rad, before step ``delay``).

    Returns:
        (B, (lead_in + T) * substeps, J) float64 servo targets (rad); (B, end - begin, J) with ``steps``.
    """
    n_joints = commands.shape[2]
    if delay:
        total = (cfg.lead_in + commands.shape[1]) * substeps
        begin, end = (0, total) if steps is None else steps
        late = expand_commands(commands, substeps, cfg, (max(begin - delay, 0), max(end - delay, 0)))
        rest = np.zeros((commands.shape[0], min(end, delay) - min(begin, delay), n_joints))
        return np.concatenate([rest, late], axis=1)
    if cfg.lead_in > commands.shape[1]:
        raise ValueError(f"lead-in of {cfg.lead_in} samples exceeds the record ({commands.shape[1]})")
    pre = commands[:, commands.shape[1] - cfg.lead_in :] * lead_in_window(cfg)[None, :, None]
    held = np.concatenate([pre, commands], axis=1)  # (B, lead+T, 8)
    nxt = np.concatenate([held[:, 1:], commands[:, :1]], axis=1)  # u[n+1], periodic at the end
    begin, end = (0, held.shape[1] * substeps) if steps is None else steps
    first, last = begin // substeps, -(-end // substeps)  # the samples whose steps are asked for
    held, nxt = held[:, first:last], nxt[:, first:last]
    frac = (np.arange(substeps) / substeps)[None, None, :, None]  # (1, 1, S, 1)
    ctrl = held[:, :, None] + (nxt - held)[:, :, None] * frac  # (B, samples, S, n_joints)
    offset = first * substeps
    return ctrl.reshape(commands.shape[0], -1, n_joints)[:, begin - offset : end - offset]


def why_broken(
    config: CommandRule,
    state: np.ndarray,
    height: np.ndarray,
    speed: np.ndarray,
    dt: float,
    first: int = 0,
    t0: float = 0.0,
) -> str | None:
    """Why a rollout broke, or None: ``state`` (n, nstate) MuJoCo's full physics state after each of
    steps ``first``, ``first`` + 1, ...; ``height`` and ``speed`` (n,) of the centre of mass at those
    steps; ``dt`` the timestep; ``t0`` the lead-in's length (record time = simulated time - t0)."""

    def at(step: int) -> str:
        t = (first + step) * dt - t0
        return f"t = {t:.2f} s" + (" (in the lead-in before the record)" if t < 0 else "")

    bad = ~np.isfinite(state).all(axis=1)
    if bad.any():
        return f"non-finite physics state at {at(int(np.argmax(bad)))}"
    expected = (np.arange(first + 1, first + state.shape[0] + 1)) * dt
    off = np.abs(state[:, 0] - expected) > 0.5 * dt  # column 0: simulated time
    if off.any():
        return f"MuJoCo reset the unstable simulation (time stopped advancing) at {at(int(np.argmax(off)))}"
    if height.max() > config.max_com_height:
        step = int(np.argmax(height > config.max_com_height))
        return (
            f"snake thrown into the air: centre of mass {height.max():.2f} m high "
            f"(limit {config.max_com_height} m) at {at(step)}"
        )
    if speed.max() > config.max_com_speed:
        step = int(np.argmax(speed > config.max_com_speed))
        return (
            f"simulation diverged: centre of mass moving at {speed.max():.1f} m/s "
            f"(limit {config.max_com_speed} m/s) at {at(step)}"
        )
    return None
