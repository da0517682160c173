"""Where the data sit in z_B: a Gaussian mixture over the training records' posterior means.

The VAE's prior N(0, I) has mass between the clusters the records form (forward and backward
undulation, say), and a z_B there decodes to a blend of the clusters' gaits, whose path no physics
follows. So the designer's sliders, Random, ``snakeloco evaluate``'s generated gaits and inverse
design's starting points draw from this density instead, fitted after training and stored in the
checkpoint's ``config.json`` (``CheckpointConfig.density``).

- Fit: full-covariance Gaussian mixture (scikit-learn's EM), the number of components chosen by BIC
  (1 .. ``max_components``); a single flow or Gaussian cannot separate clusters.
- Sample: ``LatentDensity.sample(n, seed)``, numpy only, deterministic in the seed.
- Slider axes: each component's principal axes, largest variance first, in standard deviations;
  a slider position s in component c is z_B = mean_c + axes_c s (``to_z``; ``to_axes`` inverts it).
- Flag: a z_B whose log-density is below ``threshold`` (the ``FLAG_QUANTILE`` of the training
  posteriors' own log-densities) is off the data.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

FLAG_QUANTILE = 0.01
"""A z_B less dense than 99% of the training records' posteriors is flagged as off the data."""


class LatentDensity(BaseModel):
    """A Gaussian mixture over z_B (D dimensions, K components) and the names of its components."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    weights: list[float] = Field(description="(K,) mixture weights, summing to 1.")
    means: list[list[float]] = Field(description="(K, D) component means.")
    covariances: list[list[list[float]]] = Field(description="(K, D, D) full covariances.")
    names: list[str] = Field(description="(K,) what each component's gaits do, e.g. 'forward, 17 m'.")
    threshold: float = Field(description="Log-density below which a z_B is flagged as off the data.")
    fitted_on: int = Field(ge=1, description="Posterior means the mixture was fitted to.")

    @model_validator(mode="after")
    def _consistent(self) -> LatentDensity:
        k = len(self.weights)
        means, cov = np.asarray(self.means), np.asarray(self.covariances)
        if k == 0 or means.shape[0] != k or cov.shape != (k, means.shape[1], means.shape[1]):
            raise ValueError(f"density: {k} weights, means {means.shape}, covariances {cov.shape} disagree")
        if len(self.names) != k or len(set(self.names)) != k:
            raise ValueError("density: one distinct name per component")
        if abs(sum(self.weights) - 1.0) > 1e-6 or min(self.weights) <= 0:
            raise ValueError("density: weights must be positive and sum to 1")
        if np.linalg.eigvalsh(cov).min() <= 0:
            raise ValueError("density: a covariance is not positive definite")
        return self

    # --- arrays --------------------------------------------------------------------------------

    @property
    def dim(self) -> int:
        return len(self.means[0])

    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.asarray(self.weights), np.asarray(self.means), np.asarray(self.covariances)

    def axes(self, component: int) -> np.ndarray:
        """(D, D) columns: the component's principal axes scaled by their standard deviations,
        largest first; each column's sign makes its largest entry positive (a stable convention)."""
        cov = np.asarray(self.covariances[component])
        var, vec = np.linalg.eigh(cov)
        order = np.argsort(var)[::-1]
        vec = vec[:, order] * np.sqrt(var[order])
        signs = np.sign(vec[np.abs(vec).argmax(axis=0), np.arange(vec.shape[1])])
        return vec * np.where(signs == 0, 1.0, signs)

    def to_z(self, component: int, s: np.ndarray) -> np.ndarray:
        """Slider positions s (..., D) (standard deviations along ``axes``) -> z_B (..., D)."""
        return np.asarray(self.means[component]) + np.asarray(s, np.float64) @ self.axes(component).T

    def to_axes(self, component: int, z_b: np.ndarray) -> np.ndarray:
        """z_B (..., D) -> slider positions in ``component``'s axes (``to_z``'s inverse)."""
        a = self.axes(component)
        return np.linalg.solve(a, (np.asarray(z_b, np.float64) - np.asarray(self.means[component])).T).T

    # --- densities -------------------------------------------------------------------------------

    def component_log_densities(self, z_b: np.ndarray) -> np.ndarray:
        """log(w_c N(z | mean_c, cov_c)) for z_B (B, D): (B, K)."""
        w, mu, cov = self._arrays()
        z = np.atleast_2d(np.asarray(z_b, np.float64))
        out = np.empty((len(z), len(w)))
        for c in range(len(w)):
            chol = np.linalg.cholesky(cov[c])
            y = np.linalg.solve(chol, (z - mu[c]).T)  # (D, B)
            logdet = 2 * np.log(np.diag(chol)).sum()
            out[:, c] = np.log(w[c]) - 0.5 * ((y**2).sum(0) + logdet + self.dim * np.log(2 * np.pi))
        return out

    def log_density(self, z_b: np.ndarray) -> np.ndarray:
        """log p(z_B) under the mixture, (B,)."""
        lc = self.component_log_densities(z_b)
        top = lc.max(axis=1, keepdims=True)
        return (top + np.log(np.exp(lc - top).sum(axis=1, keepdims=True)))[:, 0]

    @property
    def peak_log_density(self) -> float:
        """The highest log-density among the components' means (about the mixture's peak)."""
        return float(self.log_density(self._arrays()[1]).max())

    def component_of(self, z_b: np.ndarray) -> np.ndarray:
        """The most responsible component of each z_B (B, D): (B,) ints."""
        return self.component_log_densities(z_b).argmax(axis=1)

    def off_data(self, z_b: np.ndarray) -> np.ndarray:
        """Whether each z_B (B, D) lies where fewer records are than ``threshold`` allows: (B,) bool."""
        return self.log_density(z_b) < self.threshold

    def sample(self, n: int, seed: int = 0, component: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """n draws from the mixture (or from one ``component``): z_B (n, D) and their components (n,)."""
        w, mu, cov = self._arrays()
        rng = np.random.default_rng(seed)
        comps = (
            rng.choice(len(w), size=n, p=w / w.sum())
            if component is None
            else np.full(n, int(component), dtype=np.int64)
        )
        eps = rng.standard_normal((n, self.dim))
        chol = np.linalg.cholesky(cov)  # (K, D, D)
        z = mu[comps] + np.einsum("nij,nj->ni", chol[comps], eps)
        return z, comps


def draw_z_b(
    density: LatentDensity | None, z_b_dim: int, n: int, seed: int = 0, component: int | None = None
) -> np.ndarray:
    """n slider positions (n, z_b_dim) from ``density`` (one ``component`` of it, or all),
    deterministic in ``seed``; without a density, from the N(0, I) prior."""
    if density is None:
        if component is not None:
            raise ValueError("this checkpoint has no density, so no components to draw from")
        return np.random.default_rng(seed).standard_normal((n, z_b_dim))
    return density.sample(n, seed, component)[0]


def fit_density(
    z_b: np.ndarray, max_components: int = 6, seed: int = 0, names: list[str] | None = None
) -> LatentDensity:
    """Fit the mixture to posterior means z_B (N, D): components by BIC, threshold at the
    ``FLAG_QUANTILE`` of their own log-densities. ``names``: one per component (default "cluster c";
    ``name_components`` gives them meaning once the model can say what each component's gaits do)."""
    from sklearn.mixture import GaussianMixture

    z = np.asarray(z_b, np.float64)
    if z.ndim != 2 or len(z) < 2 or not np.isfinite(z).all():
        raise ValueError(f"fit_density needs finite (N, D) posterior means, N >= 2, got {z.shape}")
    best = None
    for k in range(1, max(1, min(max_components, len(z) // (2 * z.shape[1]))) + 1):
        gm = GaussianMixture(k, covariance_type="full", n_init=4, random_state=seed, reg_covar=1e-5).fit(z)
        bic = gm.bic(z)
        if best is None or bic < best[0]:
            best = (bic, gm)
    gm = best[1]
    k = gm.n_components
    density = LatentDensity(
        weights=(gm.weights_ / gm.weights_.sum()).tolist(),
        means=gm.means_.tolist(),
        covariances=gm.covariances_.tolist(),
        names=names or [f"cluster {c + 1}" for c in range(k)],
        threshold=0.0,
        fitted_on=len(z),
    )
    threshold = float(np.quantile(density.log_density(z), FLAG_QUANTILE))
    return density.model_copy(update={"threshold": threshold})


def direction_name(forward: float, sideways: float, heading_deg: float, precise: bool = False) -> str:
    """A path's end in words: "forward, 17 m", "backward, turning left, 9 m", "in place, turning
    right 2.2 turns" (start frame, m, deg); ``precise``: to 0.1 m and 0.01 turns, with the heading
    change of a path that does not turn ("forward, 18.8 m, heading -3°")."""
    if np.hypot(forward, sideways) < 1.0 and abs(heading_deg) >= 45:
        turns = f"{abs(heading_deg) / 360:.2f}" if precise else f"{abs(heading_deg) / 360:.1f}"
        return f"in place, turning {'left' if heading_deg > 0 else 'right'} {turns} turns"
    if precise:
        coarse = direction_name(forward, sideways, heading_deg)
        text = f"{coarse.rsplit(',', 1)[0]}, {np.hypot(forward, sideways):.1f} m"
        return text + (
            f", heading {heading_deg:+.0f}°" if abs(heading_deg) < 45 else f" ({heading_deg:+.0f}°)"
        )
    angle = np.degrees(np.arctan2(sideways, forward))
    way = (
        "forward"
        if abs(angle) <= 45
        else "backward"
        if abs(angle) >= 135
        else "left"
        if angle > 0
        else "right"
    )
    turn = "" if abs(heading_deg) < 45 else (", turning left" if heading_deg > 0 else ", turning right")
    return f"{way}{turn}, {np.hypot(forward, sideways):.0f} m"


KIND_WORDS = {"undulate": "undulation", "sidewind": "sidewinding", "roll": "rolling", "turn": "turning wave"}
"""A structured member's kind (``sim.gaits.members.Member.kind``) as a component's name begins it."""


def name_components(
    ends: np.ndarray, kinds: list[str] | None = None, weights: list[float] | None = None
) -> list[str]:
    """Distinct names of components from where their mean gaits end: ends (K, 3) = forward,
    sideways (m) and heading change (deg) of each component mean's predicted path; ``kinds`` (K),
    where the family has several, the kind of each mean's member ("rolling: right, 5 m").

    Names that would repeat are told apart by what differs: the distance to 0.1 m and the heading
    change in degrees, then each component's share of the records (``weights``), and only then a
    number: the paper family's five clusters read "forward, turning left, 1 m" three times, once
    with "(2)" and "(3)" (issue 59)."""
    ends = np.asarray(ends, np.float64)
    names = [
        (f"{KIND_WORDS.get(kinds[k], kinds[k])}: " if kinds is not None else "") + direction_name(f, s, h)
        for k, (f, s, h) in enumerate(ends)
    ]
    names = [  # to 0.1 m, 0.01 turns and the heading in degrees where the coarse name repeats
        (n.split(": ")[0] + ": " if kinds is not None else "") + direction_name(f, s, h, precise=True)
        if names.count(n) > 1
        else n
        for n, (f, s, h) in zip(names, ends, strict=True)
    ]
    if weights is not None:
        names = [
            f"{n}, {100 * w:.0f}% of the records" if names.count(n) > 1 else n
            for n, w in zip(names, weights, strict=True)
        ]
    out: list[str] = []
    for name in names:
        base, n = name, 2
        while name in out:
            name, n = f"{base} ({n})", n + 1
        out.append(name)
    return out
