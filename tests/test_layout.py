"""The house rules that keep the package usable: one import name, no MuJoCo in the model package,
the files a non-editable install needs."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import zipfile

import pytest

from snakeloco.app.designer.gui import help_text


def test_model_package_and_training_never_import_mujoco(tiny_dataset_path, tmp_path):
    """In a fresh interpreter: import the model package and its inference API, train one epoch and
    decode; MuJoCo must never have been loaded (only evaluation and calibration replay gaits)."""
    code = textwrap.dedent(
        f"""
        import sys
        import numpy as np
        import snakeloco.model
        from snakeloco.model import TrainConfig, load_pretrained
        from snakeloco.model import train
        from snakeloco.model.vae.config import ModelConfig
        assert "mujoco" not in sys.modules, "import snakeloco.model loaded mujoco"
        small = ModelConfig(z_b_dim=2, z_j_dim=2, cnn_channels=(4, 4, 4), root_hidden=8, child_hidden=4,
                            joint_embed=4, positional_channels=1)
        train({str(tiny_dataset_path)!r}, {str(tmp_path / "ckpt")!r}, TrainConfig(epochs=1, batch_size=2),
              small, log=None, progress=False)
        model = load_pretrained({str(tmp_path / "ckpt")!r})
        shape, body = model.decode(np.zeros((1, 2)))
        commands = model.commands(shape[0])
        loaded = sorted(m for m in sys.modules if m == "mujoco" or m.startswith("mujoco."))
        print("MUJOCO", loaded)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "MUJOCO []" in out.stdout


def test_the_sim_package_is_mujoco_free_and_the_simulator_module_loads_it():
    code = (
        "import sys; import snakeloco.sim as s; assert 'mujoco' not in sys.modules; "
        "assert not hasattr(s, 'Simulator'); from snakeloco.sim.physics.simulator import Simulator; "
        "assert 'mujoco' in sys.modules; print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


@pytest.mark.slow
def test_wheel_installs_under_one_name_with_its_data(tmp_path):
    """``pip install .`` puts everything under snakeloco/: no top-level sim, model or app package
    (they would collide with other projects and a user's own model.py), and the package data a
    non-editable install needs (MJCF, pretrained checkpoint, help text) is inside."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    build = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(tmp_path),
            str(root),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr
    (wheel,) = tmp_path.glob("snakeloco-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"snakeloco"}, top
    for needed in (
        "snakeloco/sim/snake.xml",
        "snakeloco/sim/physics/ground_contact.c",
        "snakeloco/sim/robots/planar6.yaml",
        "snakeloco/sim/gaits/library.json",
        "snakeloco/model/pretrained/model.safetensors",
        "snakeloco/model/pretrained/config.json",
        "snakeloco/app/designer/help.md",
        "snakeloco/sim/control/follower.py",
        "snakeloco/app/bench/users/load_driver.py",
    ):
        assert needed in names, needed
    assert not any(n.startswith("snakeloco/tests/") for n in names)


def test_help_text_names_the_controls():
    text = help_text()
    assert "Export CSV" in text and "Import CSV" in text and "z_k mode" in text


def _imports() -> dict[str, set[str]]:
    """snakeloco module -> the snakeloco modules it imports (at module level or inside functions),
    read from the source: sim, model and app are the packages in this checkout."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    graph: dict[str, set[str]] = {}
    for package in ("sim", "model", "app"):
        for path in (root / package).rglob("*.py"):
            name = "snakeloco." + ".".join(path.relative_to(root).with_suffix("").parts)
            name = name.removesuffix(".__init__")
            found = set()
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("snakeloco"):
                    found.add(node.module)
                elif isinstance(node, ast.Import):
                    found.update(a.name for a in node.names if a.name.startswith("snakeloco"))
            graph[name] = found
    return graph


def test_layers_import_downward_only_and_the_benchmarks_never_import_the_cli():
    """sim imports nothing of model or app, model nothing of app; no benchmark imports the CLI (the
    CLI sits above them); and no module imports another that imports it back (one loop: a cycle)."""
    graph = _imports()
    for module, deps in graph.items():
        layer = module.split(".")[1]
        below = {"sim": ("snakeloco.sim",), "model": ("snakeloco.sim", "snakeloco.model")}.get(layer)
        if below is not None:
            assert all(d.startswith(below) for d in deps), (module, sorted(deps))
        if module.startswith("snakeloco.app.bench"):
            assert not deps & {"snakeloco.app.cli.main", "snakeloco.app.cli.commands"}, module
    for module, deps in graph.items():  # a cycle of any length through module
        seen, todo = set(), [d for d in deps if d in graph]
        while todo:
            d = todo.pop()
            assert d != module, f"{module} imports itself back"
            if d not in seen:
                seen.add(d)
                todo.extend(x for x in graph[d] if x in graph)


def test_every_room_is_a_package_the_wheel_installs():
    """A room (a folder with an ``__init__.py`` under sim/, model/ or app/) left out of pyproject's
    package list works in an editable checkout and is missing from every wheel."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    setup = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    rooms = {
        "snakeloco." + ".".join(init.parent.relative_to(root).parts)
        for floor in ("sim", "model", "app")
        for init in (root / floor).rglob("__init__.py")
    }
    assert rooms == set(setup["packages"]), rooms ^ set(setup["packages"])
    for name in rooms:
        assert setup["package-dir"][name] == name.removeprefix("snakeloco.").replace(".", "/"), name
