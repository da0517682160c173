"""snakeloco generative model: the hierarchical VAE, its training, checkpoints and inference API.

Importing this package, the network, training and ``GaitModel`` never import MuJoCo (tested in a
subprocess); only evaluation and calibration (``snakeloco.model.evaluate``, ``.calibrate``, through
``.replays``) replay gaits in ``snakeloco.sim``'s simulator.
"""

import importlib

_WHERE = {
    "GaitModel": "api",
    "load_pretrained": "api",
    "CheckpointConfig": "checkpoint",
    "CheckpointError": "checkpoint",
    "load_checkpoint": "checkpoint",
    "save_checkpoint": "checkpoint",
    "ModelConfig": "vae.config",
    "gaussian_mmd": "vae.losses",
    "loss_terms": "vae.losses",
    "HierarchicalVAE": "vae.network",
    "PRESETS": "options",
    "TrainConfig": "options",
    "TrainPreset": "options",
    "TrainingError": "vae.train",
    "cyclic_lr": "vae.train",
    "train": "vae.train",
}
"""Where each name of the package lives: imported on first use (PEP 562), so that a command-line
``--help`` that reads only configs (``snakeloco.model.options``) never imports torch."""


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"snakeloco.model.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'snakeloco.model' has no attribute {name!r}")


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
