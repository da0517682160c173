"""snakeloco simulator: the snake robot in MuJoCo, multisine excitation, rollouts, spectra, dataset.

Imports neither ``snakeloco.model`` nor ``snakeloco.app``. Units: metres, seconds, radians, Hz.

Importing this package does not import MuJoCo. The numpy-only parts (robot constants, excitation,
spectra, the command rule, body states, path statistics, the dataset reader and writer) load at
once; the names that run the simulator (``Simulator``, ``replay``, ``generate_dataset``,
``LinkPoses``, ...) load MuJoCo on first use. So the model package and training, which need only
the former, never load the simulator.
"""

from importlib import import_module

from snakeloco.sim.body import BODY_CHANNELS, body_states
from snakeloco.sim.command_rule import SimConfig, SimulationError, expand_commands
from snakeloco.sim.dataset import (
    BODY_DOWNSAMPLE,
    BODY_RATE,
    BODY_STEPS,
    BODY_TIMES,
    SCHEMA_VERSION,
    Dataset,
    DatasetError,
    GenerateConfig,
    load_dataset,
    read_npz,
    write_npz,
)
from snakeloco.sim.excitation import RECORD, ExcitationConfig, multisine, random_phases
from snakeloco.sim.robot import (
    BODY_LENGTH,
    COMMAND_LIMIT,
    JOINT_RANGE,
    LINK_LENGTH,
    LINK_RADIUS,
    MJCF_PATH,
    N_JOINTS,
    N_LINKS,
    load_model,
    mjcf_sha256,
)
from snakeloco.sim.spectra import joint_shape, servo_response, shape_to_commands, synthesis_phase

_NEEDS_MUJOCO = {
    "ReplayResult": "snakeloco.sim.physics",
    "Simulator": "snakeloco.sim.physics",
    "replay": "snakeloco.sim.physics",
    "resolve_workers": "snakeloco.sim.threads",
    "generate_dataset": "snakeloco.sim.generate",
    "LinkPoses": "snakeloco.sim.kinematics",
}


def __getattr__(name: str):
    """The simulator's names, imported (with MuJoCo) the first time one is asked for."""
    if name in _NEEDS_MUJOCO:
        value = getattr(import_module(_NEEDS_MUJOCO[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'snakeloco.sim' has no attribute {name!r}")


__all__ = [
    "BODY_CHANNELS",
    "BODY_DOWNSAMPLE",
    "BODY_LENGTH",
    "BODY_RATE",
    "BODY_STEPS",
    "BODY_TIMES",
    "COMMAND_LIMIT",
    "JOINT_RANGE",
    "LINK_LENGTH",
    "LINK_RADIUS",
    "MJCF_PATH",
    "N_JOINTS",
    "N_LINKS",
    "RECORD",
    "SCHEMA_VERSION",
    "Dataset",
    "DatasetError",
    "ExcitationConfig",
    "GenerateConfig",
    "LinkPoses",
    "ReplayResult",
    "SimConfig",
    "SimulationError",
    "Simulator",
    "body_states",
    "expand_commands",
    "generate_dataset",
    "joint_shape",
    "load_dataset",
    "load_model",
    "mjcf_sha256",
    "multisine",
    "random_phases",
    "read_npz",
    "replay",
    "resolve_workers",
    "servo_response",
    "shape_to_commands",
    "synthesis_phase",
    "write_npz",
]
