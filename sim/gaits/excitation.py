"""Random-phase multisine excitation on exact FFT bins (paper eq. 16).

u_k(t) = U * sum_{l=1..L} sin(2 pi f_l t + phi_kl), with phi_kl uniform in [0, 2 pi), f_l log-spaced
between ``f_min`` and ``f_max`` and rounded to distinct bins of the record's FFT grid (resolution
``sample_rate / n_samples`` Hz), so each record holds a whole number of periods of every component:
no spectral leakage. One shared amplitude U per sample is scaled so that max |u| = ``command_limit``.
"""

from __future__ import annotations

import functools

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from snakeloco.sim.robot.description import COMMAND_LIMIT


class ExcitationConfig(BaseModel):
    """Sampling grid and multisine parameters shared by generation, resynthesis and replay."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    sample_rate: float = Field(20.0, gt=0, description="Command and measurement rate (Hz).")
    n_samples: int = Field(2000, gt=1, description="Samples per record (T); 2000 at 20 Hz is 100 s.")
    n_components: int = Field(8, gt=0, description="Excited frequencies per joint (L).")
    f_min: float = Field(0.05, gt=0, description="Lowest excited frequency before bin rounding (Hz).")
    f_max: float = Field(3.0, gt=0, description="Highest excited frequency before bin rounding (Hz).")
    command_limit: float = Field(
        COMMAND_LIMIT, gt=0, description="Peak |u| over the record, reached by one joint (rad)."
    )

    @model_validator(mode="after")
    def _bins_are_distinct(self) -> ExcitationConfig:
        if self.f_max >= self.sample_rate / 2:
            raise ValueError(f"f_max={self.f_max} Hz must be below Nyquist ({self.sample_rate / 2} Hz)")
        bins = self.bins
        if len(np.unique(bins)) != self.n_components or bins[0] < 1:
            raise ValueError(
                f"{self.n_components} log-spaced frequencies in {self.f_min}..{self.f_max} Hz do not "
                f"fall on distinct non-zero FFT bins of a {self.n_samples}-sample record: {bins.tolist()}"
            )
        return self

    @property
    def duration(self) -> float:
        """Record length (s)."""
        return self.n_samples / self.sample_rate

    @property
    def bins(self) -> np.ndarray:
        """Excited FFT bin indices, ascending, shape (L,) (read-only: shared by equal configs)."""
        return _round_bins(self)[0]

    @property
    def freqs(self) -> np.ndarray:
        """Excited frequencies (Hz), shape (L,); exact multiples of the bin resolution (read-only)."""
        return _round_bins(self)[1]

    @property
    def times(self) -> np.ndarray:
        """Sample times (s) of one record, shape (T,)."""
        return np.arange(self.n_samples) / self.sample_rate


@functools.lru_cache(maxsize=64)
def _round_bins(cfg: ExcitationConfig) -> tuple[np.ndarray, np.ndarray]:
    """(bins, freqs) of a config, computed once per distinct config (frozen, so hashable by its
    values): a designer's decode asks for them ~45 times (each member's shape and its frequency
    check), which cost a quarter of it."""
    target = np.geomspace(cfg.f_min, cfg.f_max, cfg.n_components)
    bins = np.round(target * cfg.n_samples / cfg.sample_rate).astype(np.int64)
    freqs = bins * (cfg.sample_rate / cfg.n_samples)
    bins.flags.writeable = freqs.flags.writeable = False
    return bins, freqs


RECORD = ExcitationConfig()
"""The product's record: 20 Hz, 2000 samples (100 s), 8 bins from 0.05 to 3 Hz, peak 2.2 rad. Datasets,
gait CSVs, the model's time axes and the designer all use it."""


def random_phases(rng: np.random.Generator, cfg: ExcitationConfig, n_joints: int) -> np.ndarray:
    """Phases phi_kl uniform in [0, 2 pi), shape (N, L), rad."""
    return rng.uniform(0.0, 2.0 * np.pi, size=(n_joints, cfg.n_components))


def multisine(phases: np.ndarray, cfg: ExcitationConfig) -> tuple[np.ndarray, float]:
    """Joint commands of one record from its phases.

    Args:
        phases: (N, L) rad.
        cfg: excitation config.

    Returns:
        commands (T, N) rad, float64, and the shared per-component amplitude U (rad).
    """
    t = cfg.times  # (T,)
    arg = 2.0 * np.pi * cfg.freqs[None, :, None] * t + phases[:, :, None]  # (n_joints, L, T)
    unit = np.sin(arg).sum(axis=1).T  # (T, n_joints)
    amplitude = cfg.command_limit / np.abs(unit).max()
    return unit * amplitude, float(amplitude)
