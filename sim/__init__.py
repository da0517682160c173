"""snakeloco simulator: the snake robot in MuJoCo, multisine excitation, rollouts, spectra, dataset.

Imports neither ``snakeloco.model`` nor ``snakeloco.app``. Units: metres, seconds, radians, Hz.

Importing this package does not import MuJoCo: it exports the numpy-only parts (robot constants,
excitation, spectra, the command rule, body states, path statistics, the dataset reader and
writer), which the model package and training need. What runs the simulator is imported from its
own module, where MuJoCo loads with it: ``sim.physics.simulator`` (``Simulator``, ``replay``,
``ReplayResult``), ``sim.data.generate`` (``generate_dataset``), ``sim.robot.kinematics`` (``LinkPoses``),
``sim.physics.threads`` (``resolve_workers``).
"""

from snakeloco.sim.data.dataset import (
    BODY_DOWNSAMPLE,
    BODY_RATE,
    BODY_STEPS,
    BODY_TIMES,
    SCHEMA_VERSION,
    Dataset,
    DatasetError,
    load_dataset,
    read_npz,
    write_npz,
)
from snakeloco.sim.data.generate_config import GenerateConfig
from snakeloco.sim.gaits.excitation import RECORD, ExcitationConfig, multisine, random_phases
from snakeloco.sim.gaits.spectra import joint_shape, servo_response, shape_to_commands, synthesis_phase
from snakeloco.sim.physics.body import BODY_CHANNELS, body_states
from snakeloco.sim.physics.command_rule import CommandRule, expand_commands
from snakeloco.sim.physics.results import SimulationError
from snakeloco.sim.robot.description import (
    BODY_LENGTH,
    COMMAND_LIMIT,
    JOINT_RANGE,
    LINK_LENGTH,
    LINK_RADIUS,
    MJCF_PATH,
    load_model,
    mjcf_sha256,
)

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
    "RECORD",
    "SCHEMA_VERSION",
    "CommandRule",
    "Dataset",
    "DatasetError",
    "ExcitationConfig",
    "GenerateConfig",
    "SimulationError",
    "body_states",
    "expand_commands",
    "joint_shape",
    "load_dataset",
    "load_model",
    "mjcf_sha256",
    "multisine",
    "random_phases",
    "read_npz",
    "servo_response",
    "shape_to_commands",
    "synthesis_phase",
    "write_npz",
]
