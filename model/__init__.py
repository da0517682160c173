"""snakeloco generative model: the hierarchical VAE, its training, checkpoints and inference API.

Importing this package, the network, training and ``GaitModel`` never import MuJoCo (tested in a
subprocess); only evaluation and calibration (``snakeloco.model.evaluate``, ``.calibrate``, through
``.replays``) replay gaits in ``snakeloco.sim``'s simulator.
"""

import importlib
import sys
import types

_WHERE = {
    "GaitModel": "api",
    "load_pretrained": "api",
    "CheckpointConfig": "checkpoint",
    "CheckpointError": "checkpoint",
    "load_checkpoint": "checkpoint",
    "save_checkpoint": "checkpoint",
    "ModelConfig": "config",
    "gaussian_mmd": "losses",
    "loss_terms": "losses",
    "HierarchicalVAE": "network",
    "PRESETS": "options",
    "TrainConfig": "options",
    "TrainPreset": "options",
    "TrainingError": "train",
    "cyclic_lr": "train",
    "train": "train",
}
"""Where each name of the package lives: imported on first use (PEP 562), so that a command-line
``--help`` that reads only configs (``snakeloco.model.options``) never imports torch."""


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"snakeloco.model.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'snakeloco.model' has no attribute {name!r}")


class _Package(types.ModuleType):
    """This package's module: ``snakeloco.model.train`` is the training function, as it always was.
    Python sets a package's attribute to each submodule it imports, so without this the first import
    of the submodule ``snakeloco.model.train`` would turn ``from snakeloco.model import train`` into
    the module (the eager imports this package made before did the same rebinding by their order)."""

    def __setattr__(self, name: str, value) -> None:
        if name == "train" and isinstance(value, types.ModuleType):
            value = value.train
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


__all__ = [
    "PRESETS",
    "CheckpointConfig",
    "CheckpointError",
    "GaitModel",
    "HierarchicalVAE",
    "ModelConfig",
    "TrainConfig",
    "TrainPreset",
    "TrainingError",
    "cyclic_lr",
    "gaussian_mmd",
    "load_checkpoint",
    "load_pretrained",
    "loss_terms",
    "save_checkpoint",
    "train",
]
