"""The subcommands' options: pydantic models whose nested configs are the library's own.

``GenerateConfig``, ``TrainConfig``, ``ModelConfig`` and ``CalibrateConfig`` are the flags of their
commands (``Flat``: without a prefix), so every default and bound lives once, beside the code that
uses it, and ``snakeloco train`` builds the model ``snakeloco.model.vae.train`` builds from Python.
Field docstrings are the ``--help`` texts. The options every command shares (checkpoint, workers,
seed, json) are ``app.cli.options``'s; the benchmarks' options sit beside them (``app.bench.options``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro
from pydantic import Field

from snakeloco.app.bench.options import Bench
from snakeloco.app.cli.options import Checkpoint, Command, Ensemble, Flat, Json, Seed, Workers, WorldName
from snakeloco.model.design.config import DesignConfig, Target
from snakeloco.model.options import (
    PRESETS,
    CalibrateConfig,
    ConsistencyConfig,
    PhysicsHeadConfig,
    SamplerConfig,
    TrainConfig,
)
from snakeloco.model.vae.config import ModelConfig
from snakeloco.sim import GenerateConfig
from snakeloco.sim.gaits.library import PRESETS as GAIT_PRESETS
from snakeloco.sim.gaits.structured import STRUCTURED_PRESETS
from snakeloco.sim.physics.backend import BackendConfig
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE


class Generate(Command):
    """Generate a training dataset: the paper's multisines or structured gaits (deterministic in N, seed and
    family; written atomically, resumable)."""

    out: Path
    """Destination: an .npz file, or a zarr store (chunked by record, for sets that outgrow memory) where it ends in .zarr."""
    config: Annotated[GenerateConfig, Flat] = GenerateConfig()
    workers: Workers = None
    """Simulation threads (default: all cores; with --backend ray, the CPUs of a Ray started here). Does not change the result."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    screened: Path | None = None
    """progress.json of an earlier run of the same options (or the shipped copy, data/screening/): its
    records are rebuilt with one replay each instead of being screened again. Does not change the result."""
    robot: Path | None = None
    """A robot description (YAML, `snakeloco robot show`) to simulate on (default: the paper's 8-joint
    snake, sim/snake.xml); its joint count sets the dataset's joint axis."""
    world: WorldName = "flat"
    """The ground the records are simulated on (docs/terrain.md): flat (the plane), a shipped world or a world YAML."""
    structured_preset: Literal[tuple(STRUCTURED_PRESETS)] | None = None  # type: ignore[valid-type]
    """With --family structured: which structured family (snakeloco.sim.STRUCTURED_PRESETS). Default
    arcs: the gait library's four kinds (undulation either way at 0.29-0.93 Hz, sidewinding,
    rolling, turning in place) at 0.3-1 of their amplitudes, mirrored or not, with 60% of the faster
    undulations curving left or right, screened by the cheap screen; the shipped structured
    checkpoint's family. compass: the same without the curves (the checkpoint shipped before);
    library: without 0.29 Hz undulation either. every: every kind of wave with free parameters and
    steering; mixed: the first structured dataset's (second waves, full screen); undulate: undulation with
    steering that survives 10% shape errors (the earlier checkpoint's)."""


class Train(Command):
    """Train the hierarchical VAE; writes the best-on-validation checkpoint and metrics.jsonl to OUT."""

    data: Path
    """Dataset .npz from `snakeloco generate`."""
    out: Path
    """Checkpoint directory (model.safetensors, config.json, metrics.jsonl)."""
    preset: Literal[tuple(PRESETS)] | None = None  # type: ignore[valid-type]
    """Start from a shipped recipe (snakeloco.model.PRESETS; paper: the shipped checkpoint); options given
    beside it override it."""
    train: Annotated[TrainConfig, Flat] = TrainConfig()
    model: Annotated[ModelConfig, Flat] = ModelConfig()


class Evaluate(Command):
    """Evaluate a checkpoint: reconstruction R^2, latent health, and generated-gait consistency vs physics."""

    data: Path
    """Held-out dataset .npz (generate it with a seed not used for training)."""
    checkpoint: Checkpoint = None
    consistency: Annotated[ConsistencyConfig, Flat] = ConsistencyConfig()
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    json: Json = False
    report: Path | None = None
    """Also write the figures, with every generated gait's statistics, to this JSON file."""
    replays: Path | None = None
    """Consistency replays (.npz): reused when the file exists (it must hold this checkpoint's decodes of the same draw), else written there after replaying; re-scores a recalibrated checkpoint without simulating."""
    floor_records: Annotated[int, Field(ge=0)] = 0
    """Replay this many of the dataset's records with 1e-3 relative command noise and report the body R^2 physics allows beside the model's (0 skips it)."""
    robustness: Annotated[int, Field(ge=0)] = 0
    """Also replay the first this many generated gaits of each z_k mode on the default variation set and report, per kind, how far each variation moves the end point against the command noise's move (0 skips it; 12 replays a gait)."""
    closed_loop: Annotated[int, Field(ge=0)] = 0
    """Also play the first this many generated gaits of each z_k mode with their steering loop on the default variation set and report, per kind, the share with a steering input and their closed-loop end errors (0 skips it; ~40 s a gait)."""


class Calibrate(Command):
    """Fine-tune the statistics head and the body decoder on replays of the model's own prior gaits (model/heads/calibrate.py); with --sampler, fit the slider density and, for the structured family, the member path head instead (model/heads/sampler.py); with --physics-head, the path head conditioned on the robot's physics (model/heads/physics_head.py)."""

    data: Path | None = None
    """The dataset .npz the checkpoint was trained on (its training split is mixed in); not read by --physics-head."""
    out: Path
    """Directory for the calibrated checkpoint (may be the input checkpoint's own)."""
    checkpoint: Checkpoint = None
    config: Annotated[CalibrateConfig, Flat] = CalibrateConfig()
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    gaits: Path | None = None
    """Replayed calibration gaits (.npz): reused when the file exists (it must hold this checkpoint's decodes of the same draw), else written there after replaying."""
    sampler: bool = False
    """Fit the slider density over the training posteriors and (structured family) the member path head on replays of the sampler's members, instead of the statistics calibration."""
    sampler_config: Annotated[SamplerConfig, tyro.conf.arg(name="sampler")] = SamplerConfig()
    physics_head: bool = False
    """Fit the member path head conditioned on the physics (friction, masses, servos, slope, latency) on replays of the sampler's members on the default variations and sampled ones, and score it on further sampler positions; written beside the checkpoint's weights (--gaits: the folder of resumable replay chunks, default OUT/physics-gaits)."""
    physics_head_config: Annotated[PhysicsHeadConfig, tyro.conf.arg(name="physics-head")] = (
        PhysicsHeadConfig()
    )


class Design(Command):
    """Design gaits for a target final position (and heading) over the 100 s record: the model proposes (CMA-ES over z_B), MuJoCo decides (each candidate replayed as a small ensemble). Writes candidate_1.csv ... (best first) and report.json to OUT."""

    out: Path
    """Directory for candidate_N.csv (gait CSV) and report.json."""
    target: Annotated[Target, Flat]
    checkpoint: Checkpoint = None
    config: Annotated[DesignConfig, Flat] = DesignConfig()
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    robot: Path | None = None
    """Robot description YAML the candidates are verified on (a fitted robot: `snakeloco fit-robot`); default: the paper's robot."""
    world: WorldName = "flat"
    """The ground the candidates are verified on (docs/terrain.md): flat (the plane), a shipped world or a world YAML."""
    robust: bool = False
    """Rank the verified candidates by their error over the default physics variations (each one replayed on every variation: docs/variations.md), not on the nominal robot alone."""
    robust_score: Literal["worst", "p90"] = "worst"
    """With --robust: rank by the worst or the 90th-percentile error over the variations."""
    closed_loop: bool = False
    """Rank the best verified candidates by where their steering loop ends on each default physics variation (each found its steering input and played closed loop following its own nominal path: docs/closed-loop.md); the candidate CSVs carry the steering input."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    json: bool = False
    """Print report.json as one JSON object on the last line."""


class Gait(Command):
    """Write a gait of the library tuned on this robot as a gait CSV (`snakeloco gait NAME --out FILE.csv`), or list the library with its measured figures (`snakeloco gait --list`)."""

    name: Annotated[Literal[tuple(GAIT_PRESETS)] | None, tyro.conf.Positional] = None  # type: ignore[valid-type]
    """The library gait to write (docs/gaits.md)."""
    out: Path | None = None
    """Destination gait CSV (the format Export CSV writes; Import CSV and snakeloco.sim.physics.simulator.replay take it)."""
    list: bool = False
    """Print the library: each gait's parameters and what it was measured to do on this robot."""
    search_robust: bool = False
    """Instead: find the most robust library-ready member per kind and direction among those the checkpoint's physics head was trained and scored on (their replays on the default variation set), confirm the best --top of each by replaying them, and print them (model/design/library.py)."""
    checkpoint: Checkpoint = None
    """With --search-robust: a checkpoint with a physics head (snakeloco calibrate --physics-head)."""
    gaits: Path | None = None
    """With --search-robust: the physics head's replay folder (default: the checkpoint's physics-gaits)."""
    top: Annotated[int, Field(ge=1)] = 3
    """With --search-robust: candidates confirmed per kind and direction."""
    draws: tuple[Literal["train", "eval"], ...] = ("train", "eval")
    """With --search-robust: the physics head's draws of members to search (trained on, scored on)."""
    workers: Workers = None
    """With --search-robust: simulation threads of the confirming replays (default: all cores)."""
    write_library: bool = False
    """With --search-robust: write the gaits found that move less than the library's gait of their kind into the library (sim/library.json), replacing its robust-* gaits."""
    json: Json = False


class Figures(Command):
    """Write PNG figures like the paper's Figs. 5-8 (fit, prior sweep, z_k samples, joint shapes) and, with --report, fig. 9 (consistency)."""

    data: Path
    """Dataset .npz for the fit figure."""
    out: Path
    """Output directory."""
    checkpoint: Checkpoint = None
    seed: Seed = 0
    """Seed of the sample choice and latent draws."""
    report: Path | None = None
    """A JSON report from `snakeloco evaluate --report` for the consistency figure (fig9)."""


class Serve(Command):
    """Open the browser gait designer (viser) on a checkpoint. The UI has no authentication."""

    host: str = "127.0.0.1"
    """Interface to bind; the default keeps the designer on this machine. Use 0.0.0.0 only on a trusted network."""
    port: Annotated[int, Field(ge=0, le=65535)] = 8080
    """TCP port (0: any free port)."""
    checkpoint: Annotated[
        tuple[str, ...],
        tyro.conf.UseAppendAction,
        tyro.conf.arg(metavar="structured|paper|DIR"),
    ] = ()
    """A checkpoint directory (a built robot's: runs/NAME/model), or a shipped one by gait family: structured (the default) or paper. Give it several times for several entries in the Gait family dropdown; the first is where a tab starts, the shipped families are offered beside them."""
    ensemble: Ensemble = ENSEMBLE_SIZE
    """Replays per gait for the predictability fan (the gait plus ensemble-1 noisy copies)."""
    robot: Path | None = None
    """Robot description YAML every replay runs on (a fitted robot: `snakeloco fit-robot`); default: the robot the first checkpoint was trained on."""
    world: WorldName = "flat"
    """The ground every replay runs on and the scene draws (docs/terrain.md); each tab can pick another in its World dropdown."""
    variations: bool = True
    """Replay each gait on the default physics variations after its ensemble (the Variations fan, at the lowest priority); --no-variations on a slow machine."""
    closed_loop: bool = True
    """Play each replayed gait with its steering loop on those variations (the closed-loop fan; each tab can turn it off); --no-closed-loop on a slow machine."""


class Robustness(Command):
    """Replay a gait CSV on the nominal robot and on each physics variation of a set (friction, anisotropy, masses, servo gains, slope, latency): where each ends and how far from the nominal end point."""

    gait: Annotated[Path, tyro.conf.Positional]
    """The gait CSV (Export CSV's format, or `snakeloco gait NAME --out`)."""
    set: str = "default"
    """default: one change at a time, the reason for each in docs/variations.md; sampled: 16 robots with every change at once; terrain: 12 worlds (rough 1-3 cm, steps 2 and 4 cm, slopes 5-15 deg ahead and left, pegs: docs/terrain.md), each measured from the flat ground's end; FILE.yaml: a list of variations (name, scale, add, set of the robot's physical and sensing fields)."""
    closed_loop: bool = False
    """Play the gait with its steering loop following its nominal path (the '# steering:' comment's input, else one found by replays; docs/closed-loop.md): end error from the path's end, arrival time, cross-track error, time at the steering limit."""
    end: Literal["arrive", "on_time"] = "arrive"
    """--closed-loop: arrive stops at the path's end (capped at 2 records); on_time runs one record."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    robot: Path | None = None
    """Robot description YAML the gait runs on (default: the paper's robot, sim/snake.xml)."""
    world: WorldName = "flat"
    """The ground the gait runs on (docs/terrain.md): flat (the plane), a shipped world or a world YAML; on a world the nominal row's end error is from the end of the path the gait takes on the flat ground."""
    workers: Workers = None
    """Simulation threads (default: all cores). Does not change the result."""
    json: Json = False


class Export(Command):
    """Export a gait CSV for a robot's stack or for colleagues: a ROS 2 JointTrajectory, a resampled CSV, gait-equation parameters, Dynamixel goal positions, or a replay page that opens with no server (html)."""

    gait: Annotated[Path, tyro.conf.Positional]
    """The gait CSV (Export CSV's format, or `snakeloco gait NAME --out`)."""
    format: Literal["ros2", "csv", "gait-equation", "dynamixel", "html", "controller"]
    """ros2: trajectory_msgs/JointTrajectory YAML (positions and velocities); csv: commands at --rate; gait-equation: the gait's named parameters (structured-family members and library gaits); dynamixel: goal positions in ticks per servo id; html: a folder whose index.html plays the replay in any browser; controller: a folder that snakeloco.sim.control.PathFollower.load reads (the gait, its steering input, the path it follows and the follower's parameters)."""
    out: Path
    """Destination file (a folder for html and controller)."""
    rate: Annotated[float, Field(gt=0, le=1000)] = 100.0
    """Samples per second of ros2, csv and dynamixel (the command rule's straight lines between the 20 Hz samples)."""
    units: Literal["rad", "deg"] = "rad"
    """Units of the csv format's angles (ros2 and dynamixel have their own)."""
    velocities: bool = False
    """csv: add vel_1..vel_N columns (rad/s or deg/s)."""
    periods: Annotated[int, Field(ge=1, le=100)] = 1
    """Records (100 s each) one after another."""
    lead_in: bool = True
    """Start with the command rule's 3 s lead-in from the straight rest pose, as the simulation does."""
    clip: bool = False
    """Clip commands beyond the robot's command limit and slow those beyond its joint speed limit (and say what was clipped) instead of refusing."""
    closed_loop: bool = False
    """ros2: also write OUT's stem + .path.yaml, the nav_msgs/Path the gait's steering loop follows with the follower's parameters (the '# steering:' comment's input, else one found by replays; docs/closed-loop.md)."""
    robot: Path | None = None
    """Robot description YAML: joint names, limits, servo ids and home offsets (default: the paper's robot)."""
    workers: Workers = None
    """html: simulation threads for the replay and its fan (default: all cores)."""


class FitRobot(Command):
    """Fit the robot's physics (friction, servo gains, ...) to measured runs of gaits on the real robot, so that replays match where it went; writes the fitted robot description (YAML) and a plot."""

    measured: tuple[Path, ...]
    """Measured runs, one CSV each: time_s,x,y,yaw[,joint_1..] (docs/calibration.md). Runs of the library's turn, sidewind and undulate gaits determine friction and servo kp best, the turn above all."""
    gait: tuple[Path, ...] = ()
    """The gait CSV each run ran, in the same order (default: the '# gait:' line of each run, beside it)."""
    out: Path
    """Destination robot description (.yaml); the plot goes beside it (.png)."""
    params: tuple[str, ...] = ("friction_along", "friction_across", "servo_kp")
    """Physical fields of the robot description to fit."""
    robot: Path | None = None
    """The robot description to start from (default: the paper's robot)."""
    generations: Annotated[int, Field(ge=1, le=500)] = 30
    """CMA-ES generations (8 candidates each, every run replayed)."""
    joint_weight: Annotated[float, Field(ge=0)] = 10.0
    """Weight of the measured joint angles' RMS misfit (rad, beyond their noise) beside the path's relative error, where runs have joint columns (0: the path alone)."""
    seed: Seed = 0
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    json: Json = False


class RobotShow(Command):
    """Check a robot description (YAML) and print its derived figures: body length, mass, servo bandwidth, MJCF hash. A bad file is refused naming the field and the reason."""

    robot: Annotated[Path | None, tyro.conf.Positional] = None
    """Robot description YAML (docs/robot.md, "Your robot"); none: the default robot (sim/snake.xml)."""
    json: Json = False


class RobotMjcf(Command):
    """Write a robot description's MuJoCo model (MJCF, built with mujoco.MjSpec)."""

    robot: Annotated[Path | None, tyro.conf.Positional] = None
    """Robot description YAML; none: the default robot."""
    out: Path
    """Destination .xml."""


class Robot(Command):
    """A robot as data: `snakeloco robot show ROBOT.yaml` (check it, print its figures), `snakeloco robot mjcf ROBOT.yaml --out X.xml` (its MuJoCo model)."""


class Build(Command):
    """From a robot description to a servable model: the structured family generated and screened on the robot, the VAE trained, the slider density and member path head calibrated, a short evaluation; each stage resumable (docs/robot.md, "Your robot")."""

    robot: Path
    """Robot description YAML (`snakeloco robot show ROBOT.yaml` checks it)."""
    out: Path
    """Build folder (runs/NAME): data, checkpoints, build.json; serve it with `snakeloco serve --checkpoint OUT` (its model/)."""
    records: Annotated[int, Field(ge=8)] = 2048
    """Training records of the structured family."""
    epochs: Annotated[int, Field(ge=1)] = 100
    """Training epochs."""
    quick: bool = False
    """Tiny sizes (24 records, 3 epochs, 6 sampler positions): every stage in a few minutes, for CI and a first try; --records and --epochs are then ignored."""
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    world: WorldName = "flat"
    """The ground the family is generated, screened and evaluated on (docs/terrain.md); the model remembers it."""


class WorldShow(Command):
    """Check a world description (YAML, or a shipped world's name: rough, steps, pegs, slope10) and print its figures. A bad file is refused naming the field and the reason."""

    world: Annotated[str, tyro.conf.Positional] = "flat"
    """World description YAML or a shipped world's name (sim/worlds/); flat: today's plane."""
    json: Json = False


class WorldMjcf(Command):
    """Write a robot on a world as a MuJoCo model (MJCF, built with mujoco.MjSpec)."""

    world: Annotated[str, tyro.conf.Positional]
    """World description YAML or a shipped world's name."""
    out: Path
    """Destination .xml."""
    robot: Path | None = None
    """Robot description YAML; none: the default robot."""


class World(Command):
    """The ground as data (docs/terrain.md): `snakeloco world show WORLD.yaml` (check it, print its figures), `snakeloco world mjcf WORLD.yaml --out X.xml [--robot ROBOT.yaml]` (a robot on it, as MuJoCo's model)."""


ROBOT_COMMANDS: dict[str, type[Command]] = {"show": RobotShow, "mjcf": RobotMjcf}
WORLD_COMMANDS: dict[str, type[Command]] = {"show": WorldShow, "mjcf": WorldMjcf}


COMMANDS: dict[str, type[Command]] = {
    "generate": Generate,
    "design": Design,
    "gait": Gait,
    "train": Train,
    "evaluate": Evaluate,
    "calibrate": Calibrate,
    "figures": Figures,
    "serve": Serve,
    "bench": Bench,  # listed here for `snakeloco --help`; `snakeloco bench ...` parses BENCHES
    "robustness": Robustness,
    "export": Export,
    "fit-robot": FitRobot,
    "robot": Robot,  # the same: `snakeloco robot ...` parses ROBOT_COMMANDS
    "world": World,  # `snakeloco world ...` parses WORLD_COMMANDS
    "build": Build,
}
