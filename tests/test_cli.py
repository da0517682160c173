"""The console script, called with explicit argument lists."""

from __future__ import annotations

import asyncio
import json
import re
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from snakeloco.app.bench.users.protocol import ProtocolClient
from snakeloco.app.cli.main import main
from snakeloco.sim import load_dataset

from helpers import free_port


def _refused(capsys, argv: list[str], says: str) -> None:
    """The command exits 2 with ``says`` in its error message (not a traceback)."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and says in capsys.readouterr().err


def test_generate_command(tmp_path, capsys, tiny_dataset):
    out = tmp_path / "g.npz"
    main(["generate", "--num-samples", "2", "--seed", "11", "--out", str(out), "--workers", "1"])
    assert "wrote" in capsys.readouterr().out
    np.testing.assert_array_equal(load_dataset(out).body, tiny_dataset.body[:2])


def _train_argv(data, out, *more: str) -> list[str]:
    """``snakeloco train`` for one epoch of DATA into OUT, then MORE options."""
    return ["train", "--data", str(data), "--out", str(out), "--epochs", "1", *more]


def test_train_command_passes_the_loss_weights(tmp_path, tiny_dataset_path, capsys):
    from snakeloco.model import load_pretrained

    out = tmp_path / "ckpt"
    args = _train_argv(tiny_dataset_path, out, "--batch-size", "2")
    main([*args, "--alpha", "4", "--beta", "3", "--gamma", "5", "--seed", "2"])
    cfg = load_pretrained(out).config
    assert (cfg.model.alpha, cfg.model.beta, cfg.model.gamma) == (4.0, 3.0, 5.0)
    assert (cfg.train["epochs"], cfg.train["seed"]) == (1, 2)
    # The number of sliders is a training choice, and the model decodes with it.
    main([*args, "--out", str(tmp_path / "four"), "--z-b-dim", "4"])
    four = load_pretrained(tmp_path / "four")
    assert four.z_b_dim == 4 and four.decode(np.zeros((1, 4)))[0].shape[0] == 1
    _refused(capsys, [*args, "--out", str(tmp_path / "nine"), "--z-b-dim", "9"], "--z-b-dim")
    assert not (tmp_path / "nine").exists()
    _refused(capsys, [*args, "--out", str(tmp_path / "none"), "--epochs", "0"], "epochs")


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["generate", "--num-samples", "0", "--out", "g.npz"], "--num-samples must be at least 1, got 0"),
        (["evaluate", "--data", "h.npz", "--ensemble", "1"], "--ensemble must be at least 2, got 1"),
        (["evaluate", "--data", "h.npz", "--prior-samples", "-1"], "--prior-samples must be at least 0"),
        (
            ["calibrate", "--data", "d.npz", "--out", "c", "--prior-samples", "0"],
            "--prior-samples must be at least 1",
        ),
        (["calibrate", "--data", "d.npz", "--out", "c", "--lr", "0"], "--lr must be positive"),
        (["train", "--data", "d.npz", "--out", "t", "--seed", "-1"], "--seed must be at least 0, got -1"),
        (["train", "--data", "d.npz", "--out", "t", "--alpha", "nan"], "--alpha must be a finite number"),
        (["serve", "--port", "70000"], "--port must be at most 65535, got 70000"),
        # viser would try port after port on a host it cannot bind, forever and without a word.
        (["serve", "--host", "999.1.1.1", "--port", "0"], "--host 999.1.1.1: not a host name or address"),
        (["serve", "--host", "192.0.2.1", "--port", "0"], "--host 192.0.2.1: cannot serve on it here"),
        (["bench", "load", "--clients", "0"], "--clients must be at least 1, got 0"),
        (["bench", "sim", "--workers", "0"], "--workers must be at least 1, got 0"),
        # Outputs are checked before an hour of replays, not when they are saved.
        (["evaluate", "--data", "h.npz", "--report", "."], "--report .: is a directory, not a file"),
        (
            ["calibrate", "--data", "d.npz", "--out", "/dev/null/c"],
            "--out /dev/null/c: /dev/null is not a directory",
        ),
        (["evaluate", "--data", "h.npz", "--replays", "/dev/null/r.npz"], "/dev/null is not a directory"),
    ],
)
def test_out_of_range_options_are_refused_before_any_work(argv, says, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # none of the named files exist: the range check comes first
    _refused(capsys, argv, says)
    assert not any(tmp_path.iterdir())


def test_serve_refuses_a_busy_port_instead_of_serving_on_the_next(capsys):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        _refused(
            capsys, ["serve", "--port", str(port)], f"--port {port}: address already in use on 127.0.0.1"
        )


def test_bench_load_without_chromium_says_what_to_install(capsys, monkeypatch, tmp_path):
    import snakeloco.app.bench.users.load_browser

    monkeypatch.setattr(snakeloco.app.bench.users.load_browser, "CHROMIUM", str(tmp_path / "no-chromium"))
    _refused(capsys, ["bench", "load", "--clients", "1", "--seconds", "1"], "apt-get install -y chromium")


def test_bench_sim_json(capsys):
    main(["bench", "sim", "--json", "--samples", "2", "--repeats", "1"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    result = json.loads(last)
    # MuJoCo steps this snake at 1e4-1e6 steps/s on one core of any machine this runs on.
    for key in ("raw_steps_per_s", "generator_steps_per_s"):
        assert 1e3 < result[key] < 1e8, (key, result[key])
    assert 0.3 < result["ratio"] < 3.0 and 0.3 < result["replay_ratio"] < 3.0, result


def test_unknown_subcommand_exits_with_usage(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["fly"])
    assert exc.value.code == 2 and "fly" in capsys.readouterr().err


def test_train_from_python_and_from_the_command_line_build_the_same_model(tmp_path, tiny_dataset_path):
    """One place per default: `snakeloco train` and `train()` with the configs' defaults give the same
    checkpoint, config and weights (training is deterministic on the CPU for a seed)."""
    from snakeloco.model import ModelConfig, TrainConfig, load_checkpoint, train

    main(["train", "--data", str(tiny_dataset_path), "--out", str(tmp_path / "cli"), "--epochs", "1"])
    train(tiny_dataset_path, tmp_path / "py", TrainConfig(epochs=1), ModelConfig(), log=None, progress=False)
    cli_net, cli_cfg = load_checkpoint(tmp_path / "cli")
    py_net, py_cfg = load_checkpoint(tmp_path / "py")
    assert cli_cfg.model == py_cfg.model == ModelConfig()
    assert {k: v for k, v in cli_cfg.train.items()} == {k: v for k, v in py_cfg.train.items()}
    for k, v in cli_net.state_dict().items():
        assert torch.equal(v, py_net.state_dict()[k]), k


def test_train_presets_are_python_objects_that_options_override(tmp_path):
    from snakeloco.app.cli.main import parse_args
    from snakeloco.model import PRESETS

    base = ["train", "--data", "d.npz", "--out", str(tmp_path / "o")]
    paper = parse_args([*base, "--preset", "paper"])
    assert paper.train == PRESETS["paper"].train and paper.model == PRESETS["paper"].model
    assert paper.train.epochs == 140
    assert parse_args([*base, "--preset=paper"]).train.epochs == 140
    tuned = parse_args([*base, "--preset", "paper", "--epochs", "3", "--alpha", "2"])
    assert tuned.train.epochs == 3 and tuned.model.alpha == 2.0 and tuned.train.cycle_epochs == 50.0
    assert parse_args(base).train.epochs == 300  # no preset: the configs' own defaults


def test_bad_checkpoint_and_dataset_end_with_a_clear_message(tmp_path, capsys, checkpoint):
    with pytest.raises(SystemExit) as exc:
        main(["serve", "--checkpoint", str(tmp_path / "nowhere"), "--port", "0"])
    assert exc.value.code == 2
    assert "missing config.json" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--data", str(bad), "--prior-samples", "0", "--checkpoint", str(checkpoint)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("snakeloco: error:") and "bad.npz" in err
    # With replays asked for, the progress bar waits for the inputs to pass: the error is all there is.
    _refused(capsys, ["evaluate", "--data", str(bad), "--checkpoint", str(checkpoint)], "bad.npz")


def test_bad_report_output_path_and_device_end_with_a_clear_message(
    tmp_path, capsys, checkpoint, tiny_dataset_path
):
    figures = ["figures", "--data", str(tiny_dataset_path), "--checkpoint", str(checkpoint)]
    not_json = tmp_path / "notes.md"
    not_json.write_text("# not a report")
    _refused(
        capsys, [*figures, "--out", str(tmp_path / "a"), "--report", str(not_json)], "not a readable JSON"
    )
    no_consistency = tmp_path / "r0.json"
    no_consistency.write_text(json.dumps({"r2_body": 0.6}))  # evaluate --prior-samples 0 writes such
    _refused(
        capsys, [*figures, "--out", str(tmp_path / "a"), "--report", str(no_consistency)], "no 'consistency'"
    )
    short = tmp_path / "r1.json"
    short.write_text(json.dumps({"consistency": {"zk_zero": {"gaits": [{"path_length_simulated": 40.0}]}}}))
    _refused(capsys, [*figures, "--out", str(tmp_path / "a"), "--report", str(short)], "path_length_decoded")
    assert not (tmp_path / "a").exists()  # the report is checked before any figure is written
    _refused(
        capsys,
        [*figures, "--report", str(tmp_path / "missing.json"), "--out", str(tmp_path / "b")],
        "missing.json",
    )
    # An --out that cannot be a directory (under a file).
    _refused(capsys, [*figures, "--out", str(not_json / "figs")], "notes.md")
    if not torch.cuda.is_available():
        out = tmp_path / "gpu"
        _refused(capsys, _train_argv(tiny_dataset_path, out, "--device", "cuda"), "no CUDA device")
        assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_serve_stops_cleanly_on_signals(tmp_path, checkpoint, sig):
    """Ctrl-C and SIGTERM end `snakeloco serve` with status 0 and free the port (a process whose
    worker threads lingered would not exit: they are joined, not abandoned)."""
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "snakeloco.app.cli.main",
            "serve",
            "--port",
            str(port),
            "--checkpoint",
            str(checkpoint),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        # Ctrl-C as a terminal delivers it: a test run started in the background (`cmd &` in a
        # script) inherits SIGINT ignored, and a Python started so never raises KeyboardInterrupt.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.2)
        else:
            raise AssertionError("the server never listened")

        async def stop_with_a_tab_open() -> str:
            # A page that joined and saw its first gait replayed: its tab's workers have all run.
            client = ProtocolClient(f"http://127.0.0.1:{port}", seed=0)
            await client.join(timeout=90)
            proc.send_signal(sig)
            out, _ = await asyncio.to_thread(proc.communicate, timeout=60)
            await client.close()
            return out

        out = asyncio.run(stop_with_a_tab_open())
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert "stopped" in out
    with socket.socket() as s:  # nothing listens any more
        assert s.connect_ex(("127.0.0.1", port)) != 0
    with socket.socket() as s:  # and a restarted server can listen there (as asyncio servers do, with
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # SO_REUSEADDR past TIME_WAIT)
        s.bind(("127.0.0.1", port))
        s.listen()


@pytest.mark.slow
def test_calibrate_command_writes_and_reuses_its_gaits(tmp_path, capsys, checkpoint, tiny_dataset_path):
    gaits = tmp_path / "gaits.npz"
    args = ["calibrate", "--data", str(tiny_dataset_path), "--checkpoint", str(checkpoint)]
    args += ["--prior-samples", "2", "--epochs", "1", "--workers", "1", "--gaits", str(gaits)]
    args += ["--sampled-samples", "1"]
    main([*args, "--out", str(tmp_path / "a")])
    first = capsys.readouterr()
    assert gaits.exists() and "replay prior gaits" in first.err and "replayed" in first.out
    main([*args, "--out", str(tmp_path / "b"), "--lr", "0.001"])
    second = capsys.readouterr()
    assert re.search(rf"reusing \d+ replayed prior gaits from {re.escape(str(gaits))}", second.out)
    assert "replay prior gaits" not in second.err
    calibration = json.loads((tmp_path / "b" / "config.json").read_text())["summary"]["calibration"]
    assert calibration["lr"] == 0.001 and calibration["epochs"] == 1
    assert calibration["sampled_samples"] == 1 and calibration["zero_samples"] == 8
    for flag_value, says in (
        ("--zero-samples=-1", "--zero-samples must be at least 0"),
        ("--sampled-samples=-1", "--sampled-samples must be at least 0"),
    ):
        out = tmp_path / flag_value.strip("-=1")
        _refused(capsys, [*args, "--out", str(out), flag_value], says)
        assert not out.exists()  # refused before replaying, not after
    # The knobs that lost (docs/model.md) are gone, not silently ignored.
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(tmp_path / "c"), "--head-loss", "mse"])
    assert exc.value.code == 2 and "--head-loss" in capsys.readouterr().err


def test_every_bench_option_is_the_parameter_of_its_function():
    """`snakeloco bench NAME` passes its options to `bench_NAME` by name (report.options): a field
    without its parameter, or a parameter with no default that no field fills, fails here."""
    import importlib
    import inspect

    from snakeloco.app.bench.options import BENCH_MODULES, BENCHES
    from snakeloco.app.bench.report import options

    for name, command in BENCHES.items():
        fn = getattr(importlib.import_module(BENCH_MODULES[name]), f"bench_{name}")
        params = inspect.signature(fn).parameters
        fields = set(command.model_fields) - {"json"}
        assert fields <= set(params), (name, fields - set(params))
        unfilled = {p for p, v in params.items() if v.default is inspect.Parameter.empty} - fields
        assert not unfilled, (name, unfilled)
        given = command.model_construct(**dict.fromkeys(command.model_fields, 0))  # any value each
        assert set(options(given)) == fields


@pytest.mark.parametrize("argv", [["--help"], ["gait", "--list"], ["design", "--help"], ["build", "--help"]])
def test_help_and_the_gait_list_import_no_torch_mujoco_or_viser(argv):
    """The command line answers at once: torch, MuJoCo and viser are imported only by the commands
    that run them (``snakeloco --help`` took 3.7-5.5 s when they were imported up front)."""
    code = (
        "import sys, contextlib, io\n"
        "from snakeloco.app.cli.main import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        f"        main({argv!r})\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print(sorted(m for m in ('torch', 'mujoco', 'viser', 'trimesh') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"
