"""What the simulator returns: a replay's measurements, a streamed replay's so far, a batch's, and
where a paused batch stopped (``sim.physics.simulator``); what it raises where a replay breaks."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from snakeloco.sim.physics.body import body_states


class Dropped(Exception):
    """The work was dropped before it ran: its caller no longer wants it (a tab's gait changed)."""


class SimulationError(RuntimeError):
    """A simulation diverged or threw the snake (``command_rule.why_broken``), or the simulator
    was closed under it; the message says how and when."""


@dataclass(frozen=True)
class ReplayResult:
    """Measured response to one record of commands at the command rate."""

    commands: np.ndarray
    """(T, n_joints) commands actually applied (rad, float64)."""
    joint_angles: np.ndarray
    """(T, n_joints) measured joint angles (rad)."""
    body: np.ndarray
    """(T, 6) body states, channels as in ``BODY_CHANNELS``."""
    times: np.ndarray
    """(T,) sample times (s), 0 at the start of the record."""
    qpos: np.ndarray
    """(T, nq) MuJoCo qpos at the sample times (world frame; for drawing the robot)."""


@dataclass(frozen=True)
class StreamedReplay:
    """What a streamed replay (``Simulator.stream``) has measured so far: its first ``samples``
    record samples (arrays as ``ReplayResult``'s, that long)."""

    samples: int
    joint_angles: np.ndarray  # (samples, n_joints) rad
    qpos: np.ndarray  # (samples, nq)
    failure: str | None  # why the simulation broke (then the stream ends), or None
    done: bool  # the whole record is in
    pos: np.ndarray = field(repr=False)  # (samples, 3) world position of the body frame
    quat: np.ndarray = field(repr=False)  # (samples, 4) its unit quaternion, wxyz

    @cached_property
    def body(self) -> np.ndarray:
        """(samples, 6) body states, computed when first asked for: a consumer that draws the path
        a few times a second does not pay for it at every chunk (the GIL other tabs wait on)."""
        with np.errstate(invalid="ignore"):
            return body_states(self.pos[None], self.quat[None])[0]


STREAM_CHUNK = 50
"""Record samples per chunk of a streamed replay: 2.5 s of record, ~17 ms of physics on one core
(a superseded replay holds its thread at most that long)."""
STREAM_POLL_S = 0.05
"""How often a stream in flight asks whether it is still wanted (``Simulator.stream``'s ``wanted``):
the shared pool drops an unwanted chunk at its turn anyway, so this only bounds how long a left
stream's thread lingers; every poll takes the GIL (docs/load.md, "STREAM_POLL_S")."""
STREAM_FIRST = 20
"""Record samples in a stream's first chunk, after the 3 s lead-in: ~27 ms of physics to the first
pose (100 samples took ~55 ms)."""


@dataclass(frozen=True)
class Paused:
    """Where a batch's rollouts stopped (``Simulator.simulate`` with ``samples``): enough to carry
    on to the same numbers as one uninterrupted rollout (the state and the solver's warm start)."""

    samples: int  # record samples measured so far
    state: np.ndarray  # (B, nstate) after the last step simulated
    warm: np.ndarray  # (B, nv)
    measured: tuple[np.ndarray, ...]  # joint angles, body position, quaternion, qpos so far (B, samples, .)
    failures: list[str | None]

    def rows(self, index: slice | list[int] | np.ndarray) -> Paused:
        """The paused rows ``index`` (to carry on with only some of them)."""
        rows = np.arange(len(self.state))[index]
        return Paused(
            self.samples,
            self.state[rows],
            self.warm[rows],
            tuple(a[rows] for a in self.measured),
            [self.failures[r] for r in rows],
        )


@dataclass(frozen=True)
class BatchResult:
    """Measurements of a batch; rows whose ``failures`` entry is not None are invalid."""

    joint_angles: np.ndarray  # (B, T, n_joints) rad
    body: np.ndarray  # (B, T, 6)
    failures: list[str | None]
    qpos: np.ndarray  # (B, T, nq) at the sample times
    paused: Paused | None = None  # where the rollouts stopped, when they stopped before the end
