"""``snakeloco generate``'s config: everything that determines a dataset's contents (numpy and
pydantic only, so the CLI and the dataset reader need no MuJoCo; ``sim.data.generate`` runs it, and a
dataset's meta stores it as ``to_meta`` writes it)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from snakeloco.sim.gaits.excitation import RECORD, ExcitationConfig
from snakeloco.sim.gaits.structured import StructuredConfig
from snakeloco.sim.physics.command_rule import CommandRule
from snakeloco.sim.robot.description import DEFAULT_ROBOT, Robot
from snakeloco.sim.world.description import DEFAULT_WORLD, World


class GenerateConfig(BaseModel):
    """Everything that determines a dataset's contents (worker count does not: results are identical)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    num_samples: int = Field(4096, ge=1, description="Number of records N.")
    seed: int = Field(0, ge=0, description="Seed of the phase draws; sample i, attempt a uses (seed, i, a).")
    max_attempts: int = Field(5, ge=1, description="Phase draws tried per sample before giving up.")
    excitation: ExcitationConfig = Field(
        RECORD,
        description="The record's sampling grid and multisine; fixed by the product (the gait CSV and "
        "the model's 500 body steps assume it), so not a command-line option.",
        json_schema_extra={"cli": False},
    )
    sim: CommandRule = Field(
        CommandRule(),
        description="The command rule and break limits (``sim.physics.command_rule``); fixed like the excitation.",
        json_schema_extra={"cli": False},
    )
    family: Literal["paper", "structured"] = Field(
        "paper",
        description="paper: the paper's random-phase multisines (chaotic on this robot); structured: "
        "randomised travelling-wave gaits that physics can predict (sim/gaits/structured.py).",
    )
    robot: Robot = Field(
        DEFAULT_ROBOT,
        description="The robot the records are simulated on (``sim.robot.description``); its joint count sets the "
        "arrays' joint axis.",
        json_schema_extra={"cli": False},
    )
    world: World = Field(
        DEFAULT_WORLD,
        description="The ground the records are simulated on (``sim.world``; default: the flat plane).",
        json_schema_extra={"cli": False},
    )
    structured: StructuredConfig = Field(
        StructuredConfig(),
        description="How the structured family draws and screens its gaits (its defaults are documented "
        "in docs/gaits.md).",
        json_schema_extra={"cli": False},
    )

    def to_meta(self) -> dict:
        """The config as a dataset's meta stores it. A paper-family config leaves the family fields
        out, exactly as datasets written before the structured family hold it, so their meta hash
        (which a checkpoint records) is unchanged."""
        paper = self.family == "paper"
        exclude = ({"family", "structured"} if paper else set()) | (
            {"robot"} if self.robot == DEFAULT_ROBOT else set()
        )  # the default robot left out too: datasets written before robots were data hash the same
        exclude |= {"world"} if self.world == DEFAULT_WORLD else set()  # and the default world
        meta = self.model_dump(mode="json", exclude=exclude or None)
        if not paper:  # undulation ranges at their defaults are left out the same way (older files)
            default = StructuredConfig()
            for name in (
                "undulate_amplitude",
                "undulate_wavenumber",
                "amplitude_scale",
                "early_seconds",
                "early_max_spread",
                "sure_spread",
                "curve",
                "curve_scale",
                "curve_frequency",
            ):
                if getattr(self.structured, name) == getattr(default, name):
                    meta["structured"].pop(name)
        return meta
