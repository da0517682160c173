"""snakeloco generative model: the hierarchical VAE, its training, checkpoints and inference API.

Importing this package, the network, training and ``GaitModel`` never import MuJoCo (tested in a
subprocess); only evaluation and calibration (``snakeloco.model.evaluate``, ``.calibrate``, through
``.replays``) replay gaits in ``snakeloco.sim``'s simulator.
"""

from snakeloco.model.api import GaitModel, load_pretrained
from snakeloco.model.checkpoint import CheckpointConfig, CheckpointError, load_checkpoint, save_checkpoint
from snakeloco.model.config import ModelConfig
from snakeloco.model.losses import gaussian_mmd, loss_terms
from snakeloco.model.network import HierarchicalVAE
from snakeloco.model.train import PRESETS, TrainConfig, TrainingError, TrainPreset, cyclic_lr, train

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
