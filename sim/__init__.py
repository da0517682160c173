"""snakeloco simulator: the snake robot in MuJoCo, multisine excitation, rollouts, spectra, dataset.

Imports neither ``model`` nor ``app``. Units: metres, seconds, radians, Hz.
"""

from sim.dataset import (
    BODY_DOWNSAMPLE,
    SCHEMA_VERSION,
    Dataset,
    DatasetError,
    GenerateConfig,
    generate_dataset,
    load_dataset,
    read_npz,
    write_npz,
)
from sim.excitation import ExcitationConfig, multisine, random_phases
from sim.physics import (
    BODY_CHANNELS,
    ReplayResult,
    SimConfig,
    SimulationError,
    Simulator,
    body_states,
    expand_commands,
    replay,
)
from sim.robot import (
    BODY_LENGTH,
    COMMAND_LIMIT,
    JOINT_RANGE,
    LINK_RADIUS,
    MJCF_PATH,
    N_JOINTS,
    load_model,
    mjcf_sha256,
)
from sim.spectra import joint_shape, servo_response, shape_to_commands, synthesis_phase

__all__ = [
    "BODY_CHANNELS",
    "BODY_DOWNSAMPLE",
    "BODY_LENGTH",
    "COMMAND_LIMIT",
    "JOINT_RANGE",
    "LINK_RADIUS",
    "MJCF_PATH",
    "N_JOINTS",
    "SCHEMA_VERSION",
    "Dataset",
    "DatasetError",
    "ExcitationConfig",
    "GenerateConfig",
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
    "servo_response",
    "shape_to_commands",
    "synthesis_phase",
    "write_npz",
]
