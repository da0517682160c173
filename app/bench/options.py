"""The benchmarks' options (``snakeloco bench NAME``), beside the benchmarks they configure; the
CLI (``app.cli.main``) parses them, the runner (``app.bench.report``) passes them by name."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from snakeloco.app.bench.users.load_driver import DWELL_S
from snakeloco.app.cli.options import Checkpoint, Command, Ensemble, Json, Seed, Workers
from snakeloco.model.design.config import DesignConfig
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE


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
    pattern: Literal["drags", "jumps", "held"] = "drags"
    """With --driver protocol: drags (a random slider dragged in 10-30 sends, then a rest of --dwell), jumps (z_B 1 jumps to a random value, the client waits for that gait's replay, rests 0.5-1.5 s; 8 moves; clients join 1-4 s apart; playback running and full rendering, as a newcomer's tab: issue 59's client) or held (the jumps, two of them sending the value z_B 1 holds, timed until the Consistency panel next says "· replay": how issue 59's client saw one client starve; held_p95_ms). The replay-ready ratio (worst client / one alone) is reported for each."""
    held_wait: Annotated[float, Field(gt=0)] = 60.0
    """With --pattern held: how long a move to the value held waits for the panel's next "· replay" (s); such a move starts nothing, so what comes is the previous gait's ensemble or fan finishing, or nothing (then it counts this long)."""
    variations: bool = False
    """Serve with the Variations fan, as `snakeloco serve` does by default (each gait replayed on 12 physics variations after its ensemble, at the pool's lowest turn but design and fits); off by default so the figures stay comparable with docs/load.md."""
    browser_page: bool = True
    """With --driver protocol: one Chromium page drags beside the protocol clients of the multi-client phase and passes the same stale checks on what it drew and exported."""
    seconds: Annotated[float, Field(gt=0)] = 60.0
    """Length of each phase."""
    json: Json = False
    checkpoint: Checkpoint = None
    ensemble: Ensemble = ENSEMBLE_SIZE
    """Replays per gait (as in `snakeloco serve`)."""
    seed: Seed = 0
    """Seed of the drag targets (with --driver protocol every client drags through the same ones, each at times of its own)."""
    render: bool = False
    """Let the pages draw the 3D view and animate the snake (software WebGL: far fewer slider updates)."""
    pin_cpus: bool = False
    """Pin the server to the first half of the CPUs and the browsers to the second half."""
    single_seconds: Annotated[float | None, Field(gt=0)] = None
    """Length of the single-client phase (default: --seconds), e.g. a short reference before a
    10-minute multi-client run that watches memory."""
    dwell: Annotated[float, Field(ge=0)] = DWELL_S
    """Seconds each page rests with the mouse up after a drag, looking at the gait it let go of (its
    replay has that long to finish; a protocol client's rests vary +-50% around it); 0: drag without
    rests, replays finish only when the drags end."""
    browser_nice: Annotated[int | None, Field(ge=0, le=19)] = None
    """Nice of the browsers (and their scheduling group). Default: 10 for --driver browser (the load
    generators level with the server's physics); 19 for the one Chromium page beside the protocol
    clients, which checks what a page draws and stands for a user's browser on another machine (at 10
    it took 0.5 of the 2 cores from the physics it shares a scheduling group with); that page also
    runs in the idle scheduling class."""


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


class _Designs(Command):
    """What the design benchmarks share: the checkpoint, how many targets, the search's size."""

    checkpoint: Checkpoint = None
    targets: Annotated[int, Field(ge=1)] = 50
    """Targets (bench design: every other one also asks for the record's heading change)."""
    candidates: Annotated[int, Field(ge=1)] = 4
    """Candidates verified per design round (x4 replays each; robust design verifies twice as many)."""
    rounds: Annotated[int, Field(ge=1)] = DesignConfig().rounds
    """Rounds of search and verification per design (bench design's baseline gets as many replays as the design used)."""
    seed: Seed = 1
    """Seed of the targets, the searches and the baseline's draws."""
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    json: Json = False


class BenchDesign(_Designs):
    """Benchmark inverse design on held-out ends (or uniform targets all round) against random draws of the data with the same physics budget (best of N replays), and its first round against the same on that round's budget: errors, heading, time to an answer."""

    data: Path | None = None
    """Held-out dataset (a seed not used in training): its records' ends are the targets."""
    reach: tuple[float, float] | None = None
    """Instead of --data: targets this far away (min max, m), uniform in distance and direction."""


class BenchRobust(_Designs):
    """Benchmark robust design (with a physics head: searching with the predicted variations fan) against nominal design on the same uniform targets, each answer's best replayed on every variation of the default set: nominal and worst-case errors, their ratio, the predicted worst beside the replayed one, time to an answer."""

    reach: tuple[float, float] = (2.0, 15.0)
    """Targets this far away (min max, m), uniform in distance and direction."""
    targets: Annotated[int, Field(ge=1)] = 20
    candidates: Annotated[int, Field(ge=1)] = 2


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


class BenchFit(Command):
    """Benchmark fit-robot: robots of known physics fitted from synthetic measured runs (3 library gaits, 1 mm / 0.5 deg noise at 50 Hz): recovered fields against the truth, held-out gaits' end error on the fitted and the nominal robot, time per fit."""

    robots: Annotated[int, Field(ge=1)] = 6
    """Perturbed robots (friction along, across and servo kp within x0.6-1.6)."""
    seed: Seed = 0
    generations: Annotated[int, Field(ge=1)] = 30
    """CMA-ES generations per fit."""
    workers: Workers = None
    """Simulation threads (default: all cores)."""
    single: bool = False
    """Instead: what one run determines (each library gait's run fitted alone, on each of --robots robots)."""
    joints: bool = False
    """The synthetic runs measure the servos' joint angles too (0.5 deg noise), as a robot whose servos report their positions."""
    gaits: tuple[str, ...] = ("turn", "sidewind", "undulate")
    """Library gaits whose runs are fitted (``sim.fit.bench.FIT_GAITS``); every other library gait and a slow undulation are held out."""
    json: Json = False


class BenchLoop(Command):
    """Benchmark closed-loop gaits against open loop on the same variations: the library's undulation and sidewinding over the default and sampled sets, with noisy sensing, started off their path, the closed loop's time against the open-loop batch's, and sampler gaits of the structured checkpoint (docs/closed-loop.md)."""

    gaits: Annotated[int, Field(ge=1)] = 64
    """Sampler gaits that travel at least --min-distance, scored over the default set."""
    seed: Seed = 0
    """Seed of the sampler's draws."""
    min_distance: Annotated[float, Field(gt=0)] = 2.0
    """Metres a sampler gait travels in its 100 s record to count."""
    sampled: Annotated[int, Field(ge=0, le=64)] = 16
    """Sampled variations beside the default set for the library gaits."""
    repeats: Annotated[int, Field(ge=1)] = 2
    """Timing: runs of each side, the best kept."""
    sections: tuple[Literal["library", "sensing", "off_path", "timing", "sampler", "designer"], ...] = (
        "library",
        "sensing",
        "off_path",
        "timing",
        "sampler",
        "designer",
    )
    checkpoint: Checkpoint = None
    workers: Workers = None
    out: Path | None = None
    """Sampler rows written gait by gait to this JSON (a rerun with it skips the gaits done)."""
    json: Json = False


class BenchTerrain(Command):
    """Benchmark what a world costs: a replay on rough ground, steps, pegs and a slope against the same replay on the flat plane (and the numpy step a machine without a C compiler runs), and the designer's first view on rough ground against the plane's (docs/terrain.md)."""

    checkpoint: Checkpoint = None
    repeats: Annotated[int, Field(ge=1)] = 3
    """Runs of each replay; the best is kept."""
    sections: tuple[Literal["replay", "designer", "library", "sampler"], ...] = ("replay", "designer")
    """replay: a replay's cost per world; designer: the first view; library, sampler: what crosses what (each gait over the terrain set, open and closed loop)."""
    gaits: Annotated[int, Field(ge=1)] = 64
    """Sampler gaits (travelling at least 2 m) over the terrain set."""
    seed: Seed = 0
    """Seed of the sampler's draws."""
    workers: Workers = None
    out: Path | None = None
    """Sampler rows written gait by gait to this JSON (a rerun with it skips the gaits done)."""
    json: Json = False


class Bench(Command):
    """Benchmarks measured side by side in one run: `snakeloco bench {sim,model,app,load,tabs,scale,design,robust,screen,fit,loop,terrain} --help`."""


BENCHES: dict[str, type[Command]] = {
    "sim": BenchSim,
    "model": BenchModel,
    "app": BenchApp,
    "load": BenchLoad,
    "tabs": BenchTabs,
    "scale": BenchScale,
    "design": BenchDesign,
    "robust": BenchRobust,
    "screen": BenchScreen,
    "fit": BenchFit,
    "loop": BenchLoop,
    "terrain": BenchTerrain,
}
BENCH_MODULES: dict[str, str] = {name: f"snakeloco.app.bench.{name}" for name in BENCHES} | {
    "sim": "snakeloco.sim.physics.bench",
    "model": "snakeloco.model.bench",
    "fit": "snakeloco.sim.fit.bench",
}
"""Where ``bench_NAME`` lives: the simulator's and the model's benchmarks in their own layers (they
import nothing of ``app``), the designer's, load, design and data-engine ones in ``app/bench/``.
Imported by name when the command runs: importing every benchmark (viser, Playwright) would add up
to a second to the start of every command."""
BENCH_HELP = Bench.__doc__
