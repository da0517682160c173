"""The subcommands' options: pydantic models whose nested configs are the library's own.

``GenerateConfig``, ``TrainConfig``, ``ModelConfig`` and ``CalibrateConfig`` are the flags of their
commands (``Flat``: without a prefix), so every default and bound lives once, beside the code that
uses it, and ``snakeloco train`` builds the model ``snakeloco.model.train`` builds from Python.
Field docstrings are the ``--help`` texts.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated, Literal

import tyro
from pydantic import BaseModel, ConfigDict, Field

from snakeloco.app.bench.load_driver import DWELL_S
from snakeloco.model.calibrate import CalibrateConfig
from snakeloco.model.config import ModelConfig
from snakeloco.model.design_config import DesignConfig, Target
from snakeloco.model.evaluate import ConsistencyConfig
from snakeloco.model.sampler import SamplerConfig
from snakeloco.model.train import PRESETS, TrainConfig
from snakeloco.sim import GenerateConfig
from snakeloco.sim.backend import BackendConfig
from snakeloco.sim.consistency import ENSEMBLE_SIZE
from snakeloco.sim.gaits import PRESETS as GAIT_PRESETS
from snakeloco.sim.structured import STRUCTURED_PRESETS

Flat = tyro.conf.OmitArgPrefixes
"""A nested config whose fields are flags of their own (``--epochs``, not ``--train.epochs``)."""
Workers = Annotated[int | None, Field(ge=1)]
Seed = Annotated[int, Field(ge=0)]  # numpy's generators take no negative seed
Ensemble = Annotated[int, Field(ge=2)]  # the replay and at least one perturbed copy: a spread needs two
Checkpoint = Annotated[
    Path | None,
    tyro.conf.arg(help="A checkpoint directory, or a shipped one by gait family: paper (the default)."),
]
Json = Annotated[bool, tyro.conf.arg(help="Print the figures as one JSON object on the last line.")]


# ``--json`` is a field named json, which shadows pydantic's deprecated ``BaseModel.json`` method: fine
# for these option models, which are never serialised that way.
warnings.filterwarnings("ignore", message='Field name "json"', category=UserWarning)


class Command(BaseModel):
    """A subcommand's options (frozen, no unknown fields, no NaN)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


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
    structured_preset: Literal[tuple(STRUCTURED_PRESETS)] | None = None  # type: ignore[valid-type]
    """With --family structured: which structured family (snakeloco.sim.STRUCTURED_PRESETS). Default
    every: every kind of wave, slow to fast, with the cheap screen; the shipped structured checkpoint's
    family. mixed: the first structured dataset's (second waves, full screen); undulate: undulation with
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


class Calibrate(Command):
    """Fine-tune the statistics head and the body decoder on replays of the model's own prior gaits (model/calibrate.py); with --sampler, fit the slider density and, for the structured family, the member path head instead (model/sampler.py)."""

    data: Path
    """The dataset .npz the checkpoint was trained on (its training split is mixed in)."""
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


class Design(Command):
    """Design gaits for a target final position (and heading) over the 100 s record: the model proposes (CMA-ES over z_B), MuJoCo decides (each candidate replayed as a small ensemble). Writes candidate_1.csv ... (best first) and report.json to OUT."""

    out: Path
    """Directory for candidate_N.csv (gait CSV) and report.json."""
    target: Annotated[Target, Flat]
    checkpoint: Checkpoint = None
    config: Annotated[DesignConfig, Flat] = DesignConfig()
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    backend: Annotated[BackendConfig, Flat] = BackendConfig()
    json: bool = False
    """Print report.json as one JSON object on the last line."""


class Gait(Command):
    """Write a gait of the library tuned on this robot as a gait CSV (`snakeloco gait NAME --out FILE.csv`), or list the library with its measured figures (`snakeloco gait --list`)."""

    name: Annotated[Literal[tuple(GAIT_PRESETS)] | None, tyro.conf.Positional] = None  # type: ignore[valid-type]
    """The library gait to write (docs/gaits.md)."""
    out: Path | None = None
    """Destination gait CSV (the format Export CSV writes; Import CSV and snakeloco.sim.replay take it)."""
    list: bool = False
    """Print the library: each gait's parameters and what it was measured to do on this robot."""


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
    checkpoint: Checkpoint = None
    ensemble: Ensemble = ENSEMBLE_SIZE
    """Replays per gait for the predictability fan (the gait plus ensemble-1 noisy copies)."""


class BenchSim(Command):
    """Benchmark the simulator: raw mujoco.rollout vs the generator, replay vs a bare mj_step loop."""

    json: Json = False
    workers: Workers = None
    """Threads (default: all cores)."""
    samples: Annotated[int | None, Field(ge=1)] = None
    """Records per batch (default: 4 per thread)."""
    repeats: Annotated[int, Field(ge=1)] = 3
    """Runs of each measurement; the best is kept."""


class BenchModel(Command):
    """Benchmark decoding: latency of one z_B (the slider path) p50/p95 and batch throughput."""

    json: Json = False
    checkpoint: Checkpoint = None
    calls: Annotated[int, Field(ge=1)] = 200
    """Timed single decodes."""


class BenchApp(Command):
    """Benchmark the designer through a real server: slider -> decoded view / replay ready, vs bare MuJoCo."""

    json: Json = False
    checkpoint: Checkpoint = None
    moves: Annotated[int, Field(ge=1)] = 20
    """Slider moves to time."""
    ensemble: Ensemble = ENSEMBLE_SIZE
    """Replays per gait (as in `snakeloco serve`)."""
    seed: Seed = 0
    """Seed of the slider values moved to."""


class BenchLoad(Command):
    """Several users drag sliders on one server (protocol clients, or headless Chromium pages): latency, bytes, exceptions, stale draws, RSS."""

    clients: Annotated[int, Field(ge=1)] = 4
    """Users in the multi-client phase (a single-client phase runs first, side by side)."""
    driver: Literal["protocol", "browser"] = "protocol"
    """protocol: each user is an asyncio websocket client speaking viser's protocol (next to no CPU, as users' browsers on their own machines), with one real Chromium page beside the multi-client phase's; browser: a Chromium page each (for machines with spare cores: --pin-cpus)."""
    browser_page: bool = True
    """With --driver protocol: one Chromium page drags beside the protocol clients of the multi-client phase and passes the same stale checks on what it drew and exported."""
    seconds: Annotated[float, Field(gt=0)] = 60.0
    """Length of each phase."""
    json: Json = False
    checkpoint: Checkpoint = None
    ensemble: Ensemble = ENSEMBLE_SIZE
    """Replays per gait (as in `snakeloco serve`)."""
    seed: Seed = 0
    """Seed of the drag targets."""
    render: bool = False
    """Let the pages draw the 3D view and animate the snake (software WebGL: far fewer slider updates)."""
    pin_cpus: bool = False
    """Pin the server to the first half of the CPUs and the browsers to the second half."""
    single_seconds: Annotated[float | None, Field(gt=0)] = None
    """Length of the single-client phase (default: --seconds), e.g. a short reference before a
    10-minute multi-client run that watches memory."""
    dwell: Annotated[float, Field(ge=0)] = DWELL_S
    """Seconds each page rests with the mouse up after a drag, looking at the gait it let go of (its
    replay has that long to finish); 0: drag without rests, replays finish only when the drags end."""
    browser_nice: Annotated[int, Field(ge=0, le=19)] = 10
    """Nice of the load-generating browsers (and their scheduling group): 10 puts them level with the
    server's replays; 15 below them, closer to browsers on other machines."""


class BenchTabs(Command):
    """Several designer tabs rendering and animating in one headless Chromium: key press -> value at the server, Export CSV time."""

    tabs: Annotated[int, Field(ge=1)] = 3
    """Pages in the one browser, all animating."""
    rounds: Annotated[int, Field(ge=1)] = 10
    """Key presses per tab (one tab after another)."""
    json: Json = False
    checkpoint: Checkpoint = None
    ensemble: Ensemble = ENSEMBLE_SIZE
    """Replays per gait (as in `snakeloco serve`)."""
    browser_nice: Annotated[int, Field(ge=0, le=19)] = 0
    """Nice of the browser's threads and its scheduling group. 0: as a person's browser runs beside the server on one machine (the server's physics then sits at +10/+15 inside its own group); `bench load` puts its load generators at +10 instead, to measure the server."""
    rendering: Literal["page", "full", "light"] = "page"
    """How the tabs draw: as each page chose ("Light rendering" ticks itself where WebGL renders in software, as in this headless Chromium), or every tab full (shadows, environment lighting, shaded grid), or every tab light."""


class BenchScale(Command):
    """Benchmark scale-out: the same records on the local and the Ray backend (throughput ratio, identical arrays, Ray's start-up), and the driver's peak memory writing and training from .npz vs zarr."""

    records: Annotated[int, Field(ge=1)] = 256
    """Records generated on each backend."""
    family: Literal["paper", "structured"] = "paper"
    """Gait family of those records."""
    seed: Seed = 7
    """Seed of the records."""
    workers: Workers = None
    """Threads here, and CPUs of the Ray instance started (default: all cores)."""
    memory_records: Annotated[int, Field(ge=0)] = 4096
    """Records written through each writer for the memory figures (0 skips them)."""
    json: Json = False


class BenchDesign(Command):
    """Benchmark inverse design on held-out ends (or uniform targets all round) against random draws of the data with the same physics budget (best of N replays), and its first round against the same on that round's budget: errors, heading, time to an answer."""

    data: Path | None = None
    """Held-out dataset (a seed not used in training): its records' ends are the targets."""
    reach: tuple[float, float] | None = None
    """Instead of --data: targets this far away (min max, m), uniform in distance and direction."""
    checkpoint: Checkpoint = None
    targets: Annotated[int, Field(ge=1)] = 50
    """Targets (every other one also asks for the record's heading change)."""
    candidates: Annotated[int, Field(ge=1)] = 4
    """Candidates verified per design round (x4 replays each)."""
    rounds: Annotated[int, Field(ge=1)] = DesignConfig().rounds
    """Rounds of search and verification per design (the baseline gets as many replays as the design used)."""
    seed: Seed = 1
    """Seed of the target choice, the searches and the baseline's draws."""
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    json: Json = False


class BenchScreen(Command):
    """Benchmark the structured family's screen: records/s of the cheap screen against the full one and against the undulation family, side by side; how often the cheap verdict differs from the full one on a sample."""

    records: Annotated[int, Field(ge=1)] = 32
    """Records generated by each screen (the undulation family: half as many)."""
    draws: Annotated[int, Field(ge=0)] = 64
    """Draws replayed in full for the agreement figures (0 skips them)."""
    seed: Seed = 5
    """Seed of the records (the sample's draws: seed + 1000)."""
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    json: Json = False


class Bench(Command):
    """Benchmarks measured side by side in one run: `snakeloco bench {sim,model,app,load,tabs,scale,design,screen} --help`."""


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
}
BENCHES: dict[str, type[Command]] = {
    "sim": BenchSim,
    "model": BenchModel,
    "app": BenchApp,
    "load": BenchLoad,
    "tabs": BenchTabs,
    "scale": BenchScale,
    "design": BenchDesign,
    "screen": BenchScreen,
}
BENCH_HELP = Bench.__doc__
