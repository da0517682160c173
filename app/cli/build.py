"""``snakeloco build``: from a robot description to a servable model, in resumable stages.

    generate   the structured family on the robot (``sim.gaits.structured``, the shipped ``arcs`` preset;
               undulation only on a planar robot), each record screened by its ensemble; a held-out
               set of another seed; then the check that the family travels at all
    train      the hierarchical VAE, the shipped structured checkpoint's recipe (``RECIPE``)
    calibrate  the slider density and the member path head (``model.heads.sampler``), which make it a
               checkpoint the designer serves
    evaluate   held-out reconstruction, and the sampler's positions decoded, projected and replayed:
               decoded vs simulated xy-path R², final-position error, the directions reached

Everything lands in one folder: ``robot.yaml``, ``data.npz``, ``heldout.npz``, ``vae/``,
``sampler-gaits.npz``, ``model/`` (serve it), ``evaluation.json`` and ``build.json``, which records
each finished stage with the options that made it and its wall time. A finished stage is skipped
when the command runs again with the same options; an interrupted generation resumes from its
``.partial`` folder, interrupted sampler replays from nothing (their file is written when they end),
and an interrupted training starts over. A stage whose options changed is refused (another ``--out``,
or remove the folder).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from snakeloco.sim.robot.description import Robot
from snakeloco.sim.world.description import DEFAULT_WORLD, World

STAGES = ("generate", "train", "calibrate", "evaluate")
STATE = "build.json"
HELDOUT_SEED_OFFSET = 2
"""The held-out set's seed: the build's + 2 (the shipped structured checkpoint's held-out records)."""
TRAVELS_BODY_LENGTHS = 1.0
"""A record travels if its 100 s end point is at least this many body lengths from its start."""
MIN_TRAVELLING = 0.25
"""Fewest records of a family that must travel for a model of it to be worth training."""


class BuildError(RuntimeError):
    """A build that cannot go on: the message says which stage, why, and what to do."""


class BuildConfig(BaseModel):
    """The sizes of a build (``snakeloco build``'s flags); defaults: the sizes the closing figures of
    docs/robot.md were measured at."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    records: int = Field(2048, ge=8, description="Training records of the structured family.")
    heldout: int = Field(96, ge=4, description="Held-out records (seed + 2) the evaluation scores.")
    epochs: int = Field(100, ge=1, description="Training epochs.")
    sampler_samples: int = Field(256, ge=4, description="Slider positions the member path head is fitted on.")
    head_epochs: int = Field(400, ge=1, description="Epochs of the member path head.")
    positions: int = Field(256, ge=4, description="Sampler positions the evaluation replays.")
    seed: int = Field(0, ge=0, description="Seed of the records, the training and the sampler.")


QUICK = BuildConfig(records=24, heldout=6, epochs=3, sampler_samples=6, head_epochs=3, positions=6)
"""``--quick``: tiny sizes that run every stage in a few minutes (what CI builds)."""


def _family(robot: Robot):
    from snakeloco.sim.gaits.structured import DEFAULT_PRESET, STRUCTURED_PRESETS, for_robot

    return for_robot(STRUCTURED_PRESETS[DEFAULT_PRESET], robot)


def stage_options(stage: str, robot: Robot, cfg: BuildConfig, world: World = DEFAULT_WORLD) -> dict:
    """What a finished ``stage`` was made with: a stage is reused only where these are unchanged."""
    base = {"robot": robot.model_dump(mode="json"), "seed": cfg.seed}
    if world != DEFAULT_WORLD:  # builds on the plane keep the options they were made with
        base["world"] = world.model_dump(mode="json")
    sizes = {
        "generate": {"records": cfg.records, "heldout": cfg.heldout},
        "train": {"records": cfg.records, "epochs": cfg.epochs},
        "calibrate": {
            "records": cfg.records,
            "epochs": cfg.epochs,
            "samples": cfg.sampler_samples,
            "head_epochs": cfg.head_epochs,
        },
        "evaluate": {
            "records": cfg.records,
            "epochs": cfg.epochs,
            "samples": cfg.sampler_samples,
            "head_epochs": cfg.head_epochs,
            "positions": cfg.positions,
            "heldout": cfg.heldout,
        },
    }[stage]
    return base | sizes


class Build:
    """One build folder: its stages, what each finished with, and how long it took."""

    def __init__(
        self,
        robot: Robot,
        out: str | Path,
        cfg: BuildConfig | None = None,
        workers: int | None = None,
        backend=None,
        log: Callable[[str], None] = print,
        world: World = DEFAULT_WORLD,
    ) -> None:
        self.robot, self.out, self.cfg, self.world = robot, Path(out), cfg or BuildConfig(), world
        self.workers, self.backend, self.log = workers, backend, log
        self.out.mkdir(parents=True, exist_ok=True)
        self.state = self._read_state()

    # --- the folder --------------------------------------------------------------------------------

    @property
    def data(self) -> Path:
        return self.out / "data.npz"

    @property
    def heldout(self) -> Path:
        return self.out / "heldout.npz"

    @property
    def checkpoint(self) -> Path:
        """The servable checkpoint (``snakeloco serve --checkpoint`` it)."""
        return self.out / "model"

    def _read_state(self) -> dict:
        path = self.out / STATE
        if not path.exists():
            return {}
        try:
            state = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise BuildError(
                f"{path}: not a build record ({exc}); remove it to start the build over"
            ) from None
        if not isinstance(state, dict):
            raise BuildError(f"{path}: not a build record; remove it to start the build over")
        return state

    def _write_state(self) -> None:
        tmp = self.out / (STATE + ".tmp")
        tmp.write_text(json.dumps(self.state, indent=1))
        tmp.replace(self.out / STATE)

    def done(self, stage: str) -> bool:
        """Whether ``stage`` finished with this build's options (a BuildError where it finished with
        others: the folder holds another build)."""
        entry = self.state.get(stage)
        if entry is None:
            return False
        wanted = stage_options(stage, self.robot, self.cfg, self.world)
        if entry.get("options") != wanted:
            changed = sorted(k for k in wanted if entry.get("options", {}).get(k) != wanted[k])
            raise BuildError(
                f"{self.out}: its {stage} stage was built with other options ({', '.join(changed)}); "
                "build into another --out, or remove the folder to start over"
            )
        return True

    def _finish(self, stage: str, seconds: float, **figures) -> None:
        self.state[stage] = {
            "options": stage_options(stage, self.robot, self.cfg, self.world),
            "seconds": round(seconds, 1),
            **figures,
        }
        for later in STAGES[STAGES.index(stage) + 1 :]:
            self.state.pop(later, None)  # made from what this stage replaced
        self._write_state()

    # --- the stages --------------------------------------------------------------------------------

    def run(self) -> dict:
        """Every stage not yet done, in order; the build record (``build.json``)."""
        (self.out / "robot.yaml").write_text(self.robot.to_yaml())
        for stage in STAGES:
            if self.done(stage):
                self.log(f"{stage}: done ({self.state[stage]['seconds']:.0f} s), skipped")
                continue
            t0 = time.perf_counter()
            figures = getattr(self, f"_{stage}")()
            self._finish(stage, time.perf_counter() - t0, **figures)
            self.log(f"{stage}: {time.perf_counter() - t0:.0f} s")
        return self.state

    def _generate(self) -> dict:
        from snakeloco.app.cli.progress import Progress
        from snakeloco.sim.data.generate import generate_dataset
        from snakeloco.sim.data.generate_config import GenerateConfig
        from snakeloco.sim.physics.results import SimulationError

        family = _family(self.robot)
        figures = {}
        for path, n, seed in (
            (self.data, self.cfg.records, self.cfg.seed),
            (self.heldout, self.cfg.heldout, self.cfg.seed + HELDOUT_SEED_OFFSET),
        ):
            gen = GenerateConfig(
                num_samples=n,
                seed=seed,
                family="structured",
                structured=family,
                robot=self.robot,
                world=self.world,
            )
            if path.exists():
                self._check_dataset(path, gen)
                continue
            try:
                with Progress(n, f"generate {path.name}", unit="record") as progress:
                    generate_dataset(gen, path, workers=self.workers, progress=progress, backend=self.backend)
            except SimulationError as exc:
                raise BuildError(
                    f"generate: on {self.robot.name} no gait of the family passes the screen for some "
                    f"records ({exc}). A robot whose gaits do not travel, or travel unpredictably, "
                    "cannot be modelled: check its friction (along < across), servos and joint pattern "
                    "with `snakeloco robot show` and `snakeloco gait`"
                ) from None
            figures[path.stem] = self._screen_figures(path)
        figures["travel"] = self._check_travel()
        return figures

    def _check_dataset(self, path: Path, gen) -> None:
        from snakeloco.sim import load_dataset

        ds = load_dataset(path)
        if ds.config != gen:
            raise BuildError(
                f"{path} was generated with other options than this build's; build into another --out, "
                "or remove the file"
            )

    def _screen_figures(self, path: Path) -> dict:
        from snakeloco.sim import load_dataset

        meta = load_dataset(path).meta
        return {"draws": meta.get("draws"), "rejection_rate": meta.get("rejection_rate")}

    def _check_travel(self) -> dict:
        """How far the family's records go; a BuildError where too few travel to be worth a model."""
        from snakeloco.sim import load_dataset

        ds = load_dataset(self.data)
        body = ds.body
        end = np.hypot(body[:, -1, 1] - body[:, 0, 1], body[:, -1, 2] - body[:, 0, 2])
        drawn = ds.meta.get("drawn") or [{}] * len(end)
        kinds = [d.get("kind", "?") for d in drawn]
        travels = end >= TRAVELS_BODY_LENGTHS * self.robot.body_length
        figures = {
            "median_m": round(float(np.median(end)), 3),
            "p90_m": round(float(np.percentile(end, 90)), 3),
            "travelling_fraction": round(float(travels.mean()), 3),
            "per_kind_median_m": {
                k: round(float(np.median(end[[i for i, kk in enumerate(kinds) if kk == k]])), 3)
                for k in sorted(set(kinds))
            },
        }
        self.log(
            f"generate: records end {figures['median_m']:.2f} m from their start (median; 90th percentile "
            f"{figures['p90_m']:.2f} m); {100 * figures['travelling_fraction']:.0f}% travel at least "
            f"{TRAVELS_BODY_LENGTHS:g} body length ({self.robot.body_length:.2f} m) in 100 s"
        )
        if figures["travelling_fraction"] < MIN_TRAVELLING:
            screen = ds.meta.get("rejection_rate")
            raise BuildError(
                f"generate: {self.robot.name} cannot move with this family: only "
                f"{100 * figures['travelling_fraction']:.0f}% of its {len(end)} screened records travel "
                f"{TRAVELS_BODY_LENGTHS:g} body length in 100 s (median {figures['median_m']:.2f} m, per kind "
                f"{figures['per_kind_median_m']}; the screen rejected "
                f"{100 * (screen or 0):.0f}% of the draws). A model of gaits that stay put would be a "
                "model of nothing: check the floor friction (along < across), servos and joint pattern"
            )
        return figures

    def _train(self) -> dict:
        from snakeloco.model.vae.config import ModelConfig
        from snakeloco.model.vae.train import PRESETS, TrainConfig, train

        preset = PRESETS["structured"]
        train_cfg = preset.train.model_copy(
            update=RECIPE["train"] | {"epochs": self.cfg.epochs, "seed": self.cfg.seed}
        )
        model_cfg: ModelConfig = preset.model.model_copy(update=RECIPE["model"])
        TrainConfig.model_validate(train_cfg.model_dump())  # the recipe's values within their bounds
        summary = train(self.data, self.out / "vae", train_cfg, model_cfg, log=self.log)
        return {"best_epoch": summary.best_epoch, "epochs_run": summary.epochs_run}

    def _calibrate(self) -> dict:
        from snakeloco.app.cli.progress import Progress
        from snakeloco.model.heads.sampler import SamplerConfig, fit_sampler
        from snakeloco.model.replays import Fit

        sc = SamplerConfig.model_validate(
            RECIPE["sampler"]
            | {"samples": self.cfg.sampler_samples, "epochs": self.cfg.head_epochs, "seed": SAMPLER_SEED}
        )
        with Progress(2 * sc.samples, "replay sampler members") as progress:
            fit = Fit(
                self.out / "vae",
                self.data,
                self.checkpoint,
                self.out / "sampler-gaits.npz",
                self.workers,
                self.backend,
                progress,
                log=self.log,
            )
            summary = fit_sampler(fit, sc)
        shutil.copy(self.out / "vae" / "metrics.jsonl", self.checkpoint / "metrics.jsonl")
        return {"components": summary.get("components"), "head": summary.get("head", {})}

    def _evaluate(self) -> dict:
        from snakeloco.app.cli.progress import Progress
        from snakeloco.model.evaluate import ConsistencyConfig, evaluate

        cc = ConsistencyConfig(
            prior_samples=self.cfg.positions, positions="sampler", ensemble=2, seed=7, zk_modes=("zk_zero",)
        )
        with Progress(cc.prior_samples, "evaluate: replay sampler positions") as progress:
            report = evaluate(
                self.checkpoint,
                self.heldout,
                cc,
                self.workers,
                progress,
                self.out / "replays.npz",
                backend=self.backend,
                floor_records=FLOOR_RECORDS,
            )
        (self.out / "evaluation.json").write_text(json.dumps(report, indent=1))
        return {"figures": build_figures(report)}


FLOOR_RECORDS = 96
"""Held-out records replayed with command noise (``model.evaluate.physics_floor``): which body channels
physics itself repeats, the ones a body R^2 can judge a model by (a planar snake's vertical, roll
and pitch are contact jitter)."""
SAMPLER_SEED = 1000
"""Seed of the sampler's slider positions (``SamplerConfig.seed``'s default)."""
RECIPE = {
    "train": {"cycle_epochs": 50.0, "gamma": 1.0},
    "model": {"joint_latent_dropout": 0.9, "encoder_sees_shape": True},
    "sampler": {
        "max_components": 12,
        "head_inputs": "named_curve",
        "mirror": True,
        "hidden": 256,
        "head_path": "heading",
        "xy_floor": 1.0,
    },
}
"""The shipped structured checkpoint's recipe (docs/model.md, "The shipped structured checkpoint"),
which every build trains and calibrates with."""

SECTORS = ("forward", "left", "backward", "right")


def sector(heading_deg: float) -> str:
    """The direction sector of an end point's bearing (deg, left +): forward is within 45 deg of
    the start heading."""
    return SECTORS[int(((heading_deg + 45.0) % 360.0) // 90.0)]


def build_figures(report: dict) -> dict:
    """The figures a build is judged by, from ``evaluate``'s report: held-out joint shape and body
    R² (the VAE's reconstruction, and the member path head's path from the gait alone), and over the sampler positions decoded vs simulated xy-path R² and final-position error
    (medians) and the number of end points in each direction sector."""
    c = report.get("consistency", {}).get("zk_zero", {})
    rows = c.get("gaits", [])
    sectors = dict.fromkeys(SECTORS, 0)
    for r in rows:
        direction = r.get("direction_deg", r.get("heading_deg"))  # heading_deg: an older report's name
        if direction is not None and math.isfinite(direction):
            sectors[sector(direction)] += 1
    return {
        "shape_r2": report.get("r2_shape"),
        "body_r2": report.get("r2_body"),  # the designer's path of a record's member, from its gait alone
        "body_r2_reconstruction": report.get(
            "r2_body_raw", report.get("r2_body")
        ),  # the VAE's encode -> decode
        # over the channels physics repeats (``model.evaluate.repeated_channels``), where measured
        "body_channels_repeated": report.get("body_channels_repeated"),
        "body_r2_repeated": report.get("r2_body_repeated"),
        "body_r2_reconstruction_repeated": report.get("r2_body_raw_repeated"),
        "positions": c.get("n_gaits"),
        "broken": c.get("n_broken"),
        "xy_r2_median": c.get("xy_r2"),
        "final_error_median": c.get("final_error_rel"),
        "sectors": sectors,
        "off_data_fraction": c.get("off_data_fraction"),
    }
