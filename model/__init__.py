"""snakeloco generative model: the hierarchical VAE, its training, checkpoints and evaluation.

The network and training know nothing of MuJoCo; only evaluation replays gaits through ``sim``.
"""

from model.api import GaitModel, load_pretrained
from model.checkpoint import CheckpointConfig, CheckpointError, load_checkpoint, save_checkpoint
from model.network import HierarchicalVAE, ModelConfig, gaussian_mmd, loss_terms
from model.train import TrainConfig, TrainingError, cyclic_lr, train

__all__ = [
    "CheckpointConfig",
    "CheckpointError",
    "GaitModel",
    "HierarchicalVAE",
    "ModelConfig",
    "TrainConfig",
    "TrainingError",
    "cyclic_lr",
    "gaussian_mmd",
    "load_checkpoint",
    "load_pretrained",
    "loss_terms",
    "save_checkpoint",
    "train",
]
