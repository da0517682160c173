"""Replaying decoded gaits in MuJoCo, and keeping the replays in a checked side file.

Evaluation (the consistency check), calibration (the model's own prior gaits) and design
verification all do the same thing: decode latents to joint shapes, resynthesise commands as the
designer does (``GaitModel.commands``: servo-compensated inverse FFT), replay each gait once or as
an ensemble (the commands plus K - 1 copies with ``ENSEMBLE_NOISE`` relative noise), and keep the
body series at the model's rate. Replays cost minutes to an hour, so they can be written to an .npz
side file and read back instead of replaying; a side file is accepted only for the same draw
(``drawn``: counts, seeds, temperatures), the same noise, the same robot (MJCF hash) and the same
decoded gaits (a checkpoint whose decodes differ needs its own replays).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snakeloco.model.api import GaitModel, load_pretrained
from snakeloco.sim import Dataset, DatasetError, load_dataset, mjcf_sha256, read_npz, write_npz
from snakeloco.sim.physics.backend import BackendConfig, open_backend, simulate_bodies
from snakeloco.sim.scores.consistency import ENSEMBLE_NOISE, perturbed_commands

DECODE_TOLERANCE = 1e-4
"""Largest difference (rad) between stored and fresh decodes of the same latents that still counts
as the same gait: one z_B and a batch of them decode 3.6e-7 rad apart on one CPU."""


@dataclass(frozen=True)
class Fit:
    """A fit after training (``model.heads.calibrate.calibrate``, ``model.heads.sampler.fit_sampler``; the
    command ``snakeloco calibrate``): the checkpoint it starts from, the dataset that checkpoint was
    trained on, where the fitted checkpoint goes and where the replays it fits on are kept; where
    those replays run (``workers`` threads or a Ray cluster's CPUs, ``backend``) and who hears of
    them (``progress``: replays done since its last call; ``log``: lines of what was done)."""

    checkpoint: str | Path | None
    data: str | Path
    out: str | Path
    gaits_path: str | Path | None = None
    workers: int | None = None
    backend: BackendConfig | None = None
    progress: Callable[[int], None] | None = None
    log: Callable[[str], None] | None = print

    def load(self) -> tuple[GaitModel, Dataset]:
        """The checkpoint and the dataset, a robot warning logged."""
        model = load_pretrained(self.checkpoint)
        if warning := model.robot_warning():
            self.say(f"warning: {warning}")
        return model, load_dataset(self.data)

    def open_backend(self, robot=None, world=None):
        """The backend the replays run on, on ``robot`` and ``world`` (a checkpoint's ``GaitModel.robot``
        and ``.world``; None: the default robot, the flat plane); close it when done."""
        return open_backend(self.backend, self.workers, robot=robot, world=world)

    def say(self, line: str) -> None:
        """Log ``line`` where the fit has a log."""
        if self.log:
            self.log(line)


def replay_shapes(
    model: GaitModel,
    shapes: np.ndarray,
    backend,
    ensemble: int = 1,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
    own: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Replay decoded joint shapes (n, n_joints, L, 2) rad, each as an ensemble of ``ensemble`` replays.

    Gait i's perturbed members use noise seeded with ``seed + i``; member 0 is the unperturbed
    replay (left out with ``own=False``, for a gait whose own replay ran already: the members that
    remain are the same noisy copies). ``backend`` is where they run (``sim.physics.backend.open_backend``:
    this machine's cores or Ray; the caller closes it); the commands of a few gaits are made at a
    time, so memory stays bounded. ``progress`` is called with the number of gaits finished after
    each batch.

    Returns:
        bodies (n, K, 500, 6) float32, the body series at the model's 5 Hz (zeros where a replay
        broke), and ok (n, K) bool, which replays ran cleanly; K = ``ensemble`` (``- 1`` without
        the own replay).
    """
    n, cfg = len(shapes), model.config.model
    first = 0 if own else 1
    members = ensemble - first
    bodies = np.zeros((n, members, cfg.body_steps, cfg.body_channels), np.float32)
    ok = np.zeros((n, members), bool)
    # Enough gaits per job to keep a backend's threads busy (or a Ray task worth its overhead);
    # records are independent, so the batching changes nothing in the results.
    per_batch = max(1, backend.replays_per_job // max(members, 1))
    batches = [np.arange(start, min(n, start + per_batch)) for start in range(0, n, per_batch)]

    def jobs():
        for idx in batches:
            commands = model.commands(shapes[idx])  # (b, T, n_joints)
            if ensemble > 1:
                commands = np.concatenate(
                    [
                        perturbed_commands(c, ensemble, seed=seed + int(i))[first:]
                        for c, i in zip(commands, idx, strict=True)
                    ]
                )  # (b K, T, 8)
            yield commands

    if members == 0:
        return bodies, ok
    for b, (body, failures) in backend.map(simulate_bodies, jobs()):
        idx = batches[b]
        ran = np.array([f is None for f in failures]).reshape(len(idx), members)
        ok[idx] = ran
        bodies[idx] = np.where(ran[..., None, None], body.reshape(len(idx), members, *bodies.shape[2:]), 0.0)
        if progress is not None:
            progress(len(idx))
    return bodies, ok


def save_side_file(path: str | Path, drawn: dict, robot=None, **arrays: np.ndarray) -> None:
    """Write replays (``arrays``) with what they were drawn from (``drawn``: scalars), the ensemble
    noise and the MJCF hash of the robot they ran on (None: the default), atomically
    (``sim.write_npz``: no pickle)."""
    write_npz(
        path,
        noise=np.float64(ENSEMBLE_NOISE),
        mjcf_sha256=np.array(mjcf_sha256(robot)),
        **{k: np.asarray(v) for k, v in drawn.items()},
        **arrays,
    )


def load_side_file(
    path: str | Path, what: str, drawn: dict, need: list[str], robot=None
) -> dict[str, np.ndarray]:
    """Read a side file written by ``save_side_file`` for the same draw on the same robot.

    ``what`` names the kind of file in messages. Raises ``DatasetError`` naming the difference: a
    file that is not such a file, another draw (``drawn``), another noise level, or another robot.
    """
    path = Path(path)
    stored = read_npz(path, what, ["noise", "mjcf_sha256", *drawn, *need])
    asked = {"noise": ENSEMBLE_NOISE, **drawn}
    held = {k: _scalar(stored[k]) for k in asked}
    if held != {k: _scalar(np.asarray(v)) for k, v in asked.items()}:
        raise DatasetError(f"{path}: {what} of {held}; this run asks for {asked}")
    if str(stored["mjcf_sha256"]) != mjcf_sha256(robot):
        raise DatasetError(
            f"{path}: replayed on another robot model than {(robot.name if robot else 'sim/snake.xml')} "
            "(its MJCF hash differs); replay again"
        )
    return stored


def check_same_gaits(path: str | Path, stored: np.ndarray, fresh: np.ndarray, label: str = "") -> None:
    """A ``DatasetError`` unless the stored decoded shapes are this checkpoint's (``fresh``)."""
    gap = float(np.abs(stored - fresh).max()) if stored.shape == fresh.shape else float("inf")
    if gap > DECODE_TOLERANCE:
        where = f" ({label})" if label else ""
        raise DatasetError(
            f"{path}: these replays are of gaits decoded by another checkpoint{where}: decoding their "
            f"latents again differs by up to {gap:.3g} rad; replay them for this checkpoint"
        )


def _scalar(a: np.ndarray):
    """A stored 0-d array as a Python value (lists for arrays), for comparing draws."""
    return a.item() if a.ndim == 0 else a.tolist()
