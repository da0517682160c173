"""What an inverse design is asked (``Target``) and how it searches and verifies (``DesignConfig``);
``model.design.search`` runs it."""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, model_validator

OUTSIDE_COST = 10.0
"""Metres of error per unit of z_B radius beyond the data's bulk (``design.prior_cost``)."""
VERIFY_ENSEMBLE = 4
"""Replays per reported candidate: its own and 3 with 1e-3 relative command noise."""


class Target(BaseModel):
    """Where the gait should take the snake in the 100 s record, in the frame of its start."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    forward: float = Field(description="Final forward displacement (m).")
    sideways: float = Field(description="Final sideways displacement (m; positive to the left).")
    heading: float | None = Field(None, description="Heading change (degrees, positive to the left).")
    max_roll: float | None = Field(None, gt=0, description="Largest |net roll| allowed (rad).")

    @property
    def distance(self) -> float:
        return math.hypot(self.forward, self.sideways)


class DesignConfig(BaseModel):
    """How the search and the verification run."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    candidates: int = Field(4, ge=1, le=32, description="Candidates verified in MuJoCo and reported.")
    seed: int = Field(
        0, ge=0, description="Seed of the search (prior screen, CMA-ES) and the ensemble noise."
    )
    tolerance: float | None = Field(
        None,
        gt=0,
        description="Distance (m) within which a target counts as met (default: 10% of the "
        "target distance, at least 0.25 m).",
    )
    heading_tolerance: float = Field(
        15.0, gt=0, description="Heading error (deg) within which it counts as met."
    )
    screen: int = Field(512, ge=1, description="Prior draws decoded to pick the starts of the search.")
    starts: int = Field(8, ge=1, description="CMA-ES runs, from the best distinct draws of the screen.")
    generations: int = Field(40, ge=1, description="CMA-ES generations per run.")
    population: int = Field(12, ge=4, description="CMA-ES population per generation.")
    sigma0: float = Field(0.5, gt=0, description="CMA-ES initial step (prior units).")
    prior_weight: float = Field(
        0.02,
        ge=0,
        description="Metres of error one nat of negative log density of the slider sampler (of "
        "the N(0, I) prior, |z|^2 / 2, without one) costs. 0.02: on the compass checkpoint "
        "(docs/design.md) 0.05 held the search inside the bulk short of targets at the family's edge.",
    )
    prior_margin: float = Field(
        3.0,
        gt=0,
        description="Without a slider density: z_B farther than sqrt(D_b) + this from the prior's "
        "mean (beyond ~99.9% of its mass, where the model saw no data) costs OUTSIDE_COST metres "
        "per unit. With one, its off-data threshold is the bulk's edge.",
    )
    heading_weight: float = Field(0.05, ge=0, description="Metres of error one degree of heading costs.")
    roll_weight: float = Field(
        2.0, ge=0, description="Metres of error one radian of roll over the bound costs."
    )
    ensemble: int = Field(
        VERIFY_ENSEMBLE,
        ge=2,
        description="Replays per reported candidate: its own (each round replays only that) and "
        "ensemble - 1 with 1e-3 relative command noise, run once the rounds are done.",
    )
    rounds: int = Field(
        6,
        ge=1,
        description="Rounds of search and verification. After the first, each of the best verified "
        "candidates is searched again near its z_B for the target moved by what physics did otherwise "
        "than its decoded path (its replay's end minus the decoded end), and the new candidates are "
        "verified. Stops at the first round that meets the target.",
    )
    refine_sigma: float = Field(0.2, gt=0, description="CMA-ES initial step of a refinement (prior units).")
    refine_generations: int = Field(20, ge=1, description="CMA-ES generations of a refinement.")
    reach_check: bool = Field(
        True,
        description="Answer a target far beyond the family's reach at once with its nearest gait "
        "(``model.design.search.nearest_in_reach``) instead of searching; off: always search (``bench design`` "
        "measures the search itself).",
        json_schema_extra={"cli": False},
    )

    @model_validator(mode="after")
    def _enough_starts(self) -> DesignConfig:
        if self.screen < self.starts:
            raise ValueError(f"screen ({self.screen}) must hold at least the {self.starts} starts")
        return self

    def tolerance_for(self, target: Target) -> float:
        return self.tolerance if self.tolerance is not None else max(0.1 * target.distance, 0.25)
