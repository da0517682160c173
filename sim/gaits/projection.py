"""The projection of a joint shape onto the structured family's members (``sim.gaits.members``).

``project`` takes a *commanded* joint shape (N, L, 2) rad (a decoded shape divided by the servo
gain) and returns the member of ``StructuredConfig`` closest to it in the least-squares sense over
the complex coefficients, with the relative residual of the fit. For each allowed kind and
frequency the amplitudes and phase offsets have closed forms given the spatial frequency nu, and
nu is found on a grid over the family's range and polished by Newton's method on the derivative
of the fit (so an exact member projects onto itself to rounding). Parameters are clipped to the
family's ranges: a projected member is one the family could have drawn (before screening). The
mixed preset's optional second wave is not a member parameter: projection drops it (the shipped
structured family has none).
"""

from __future__ import annotations

import functools

import numpy as np

from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.gaits.library import GaitEquation, layout
from snakeloco.sim.gaits.members import FREQS, STEERING_BIN, Member
from snakeloco.sim.gaits.spectra import shape_to_commands
from snakeloco.sim.gaits.structured import (
    KINDS,
    NU_RANGES,
    StructuredConfig,
    curve_wave,
    for_robot,
    library_gait,
    undulation_scale,
)
from snakeloco.sim.robot.description import Robot

SPECIFIC_FIRST = ("undulate", "roll", "sidewind", "turn")
"""Kinds from the most to the least constrained: an undulation is also a turning wave with no pitch,
so a shape both fit equally well is called by the more specific name."""
SPECIFIC_MARGIN = 1.5
"""A less constrained kind must fit a shape this many times better (relative residual) than a more
specific one to be chosen. A decoded shape is never exactly one kind's, and the kind with the most
freedom (turning: free pitch and yaw waves) absorbs the most of any shape: on 96 held-out records of
the every family, the least residual alone named the record's own kind for 28% of their decoded
shapes, this margin for 92% (docs/every-model.md). An exact member still projects onto itself (its
own kind's residual is 0)."""
GRID = 721
"""Spatial-frequency grid points per fit before Newton's polish (0.003 rad per module apart on the
widest range): fine enough that the grid's best lies in the basin of the global optimum."""


# --- the fit ---------------------------------------------------------------------------------------


def _sums(z: np.ndarray, k: np.ndarray, nu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S(nu) = sum_k z_k e^{-i nu k} and its first two derivatives in nu, for nu (G,): each (G,)."""
    e = z[None, :] * np.exp(-1j * nu[:, None] * k[None, :])  # (G, n)
    return e.sum(1), (-1j * k * e).sum(1), (-(k**2) * e).sum(1)


def _term(s: np.ndarray, ds: np.ndarray, dds: np.ndarray, free: bool):
    """A group's fitted amplitude times its size, t(nu), and its two derivatives: Re S with the
    group's phase fixed by the family, |S| with it free."""
    if not free:
        return s.real, ds.real, dds.real
    mag = np.maximum(np.abs(s), 1e-30)  # its cube stays a normal float
    cross = (np.conj(s) * ds).real
    return mag, cross / mag, (np.abs(ds) ** 2 + (np.conj(s) * dds).real) / mag - cross**2 / mag**3


def _objective(groups: list[tuple[np.ndarray, np.ndarray, bool]], nu: np.ndarray, shared: bool):
    """F(nu) = what the fit explains (sum |z|^2 minus the residual) and F', F'' over nu (G,).

    ``groups``: (z, modules, phase free) per joint group sharing nu. Independent amplitudes:
    F = sum_g max(t_g, 0)^2 / n_g; one shared amplitude (rolling): F = (sum_g t_g)^2 / sum_g n_g.
    """
    ts = [_term(*_sums(z, k, nu), free) for z, k, free in groups]
    if shared:
        n = sum(len(z) for z, _, _ in groups)
        t, dt, ddt = (sum(parts) for parts in zip(*ts, strict=True))
        t = np.maximum(t, 0.0)
        return t**2 / n, 2 * t * dt / n, 2 * (dt**2 + t * ddt) / n
    f = df = ddf = 0.0
    for (z, _, _), (t, dt, ddt) in zip(groups, ts, strict=True):
        on = t > 0
        f = f + np.where(on, t**2, 0.0) / len(z)
        df = df + np.where(on, 2 * t * dt, 0.0) / len(z)
        ddf = ddf + np.where(on, 2 * (dt**2 + t * ddt), 0.0) / len(z)
    return f, df, ddf


def _polish(groups, nu: float, lo: float, hi: float, shared: bool) -> float:
    """Newton's method on F from ``nu``, kept inside its half of [-hi, -lo] u [lo, hi]."""
    sign = 1.0 if nu >= 0 else -1.0
    for _ in range(50):
        _, df, ddf = _objective(groups, np.array([nu]), shared)
        if not ddf[0] < 0:
            break  # not in a maximum's bowl (a clipped amplitude): keep the grid's best
        step = float(df[0] / ddf[0])
        new = sign * float(np.clip(sign * (nu - step), lo, hi))
        if new == nu:
            break
        nu = new
        if abs(step) < 1e-15:
            break
    return nu


def _best_nu(groups, lo: float, hi: float, shared: bool = False) -> float:
    """The spatial frequency in [-hi, -lo] u [lo, hi] that maximises the fit: grid, then Newton.

    A wave on joints two modules apart with a free phase fits nu and nu -+ pi alike (aliases). Where
    the grid's best polishes onto a range edge (its maximum lies just outside), the other half's best
    is polished too and the better kept: a draw at nu_yaw 1.54 is found there, not as -1.6."""
    half = np.linspace(lo, hi, GRID // 2 + 1)
    grid = np.concatenate([-half[::-1], half])
    f, _, _ = _objective(groups, grid, shared)
    i = int(np.argmax(f))
    nu = _polish(groups, float(grid[i]), lo, hi, shared)
    if abs(nu) in (lo, hi):
        other = np.flatnonzero((grid >= 0) != (grid[i] >= 0))
        alt = _polish(groups, float(grid[other[np.argmax(f[other])]]), lo, hi, shared)
        if (
            _objective(groups, np.array([alt]), shared)[0][0]
            > _objective(groups, np.array([nu]), shared)[0][0]
        ):
            nu = alt
    return nu


def _amplitude(z: np.ndarray, k: np.ndarray, nu: float, free: bool) -> tuple[float, float]:
    """A group's least-squares amplitude (>= 0) and phase offset (0 where fixed) at ``nu``."""
    s = (z * np.exp(-1j * nu * k)).sum() / len(z)
    if free:
        return float(abs(s)), float(np.angle(s))
    return max(float(s.real), 0.0), 0.0


def _fit_wave(
    kind: str, c: np.ndarray, frequency: float, cfg: StructuredConfig, robot: Robot
) -> GaitEquation:
    """The ``kind`` wave at ``frequency`` closest to commanded coefficients c (N,) complex at its bin.

    The wave's coefficients are A e^{i(phi_k - pi/2)} (``GaitEquation.shape``), so z = c e^{i pi/2}
    holds A e^{i phi_k}: pitch phase nu_p k, yaw phase nu_y k + delta.
    """
    z = c * 1j
    modules, pitch = layout(robot)
    zp, zy, kp, ky = z[pitch], z[~pitch], modules[pitch].astype(float), modules[~pitch].astype(float)
    if kind == "undulate":
        lo, hi = cfg.undulate_wavenumber
        nu = _best_nu([(zy, ky, False)], lo, hi)
        a, _ = _amplitude(zy, ky, nu, False)
        a = float(np.clip(a, *cfg.amplitude_ranges(kind)[1]))
        return GaitEquation(a_yaw=a, nu_yaw=nu, frequency=frequency)
    if kind == "turn":  # independent waves: two separate fits
        nu_p = _best_nu([(zp, kp, False)], *NU_RANGES["turn_pitch"])
        nu_y = _best_nu([(zy, ky, True)], *NU_RANGES["turn_yaw"])
        nu_p = float(np.clip(nu_p, -NU_RANGES["turn_pitch"][1], NU_RANGES["turn_pitch"][1]))
        nu_y = float(np.clip(nu_y, -NU_RANGES["turn_yaw"][1], NU_RANGES["turn_yaw"][1]))
    else:
        nu = _best_nu([(zp, kp, False), (zy, ky, True)], *NU_RANGES[kind], shared=kind == "roll")
        nu_p = nu_y = nu
    a_p, _ = _amplitude(zp, kp, nu_p, False)
    a_y, delta = _amplitude(zy, ky, nu_y, True)
    (p_lo, p_hi), (y_lo, y_hi) = cfg.amplitude_ranges(kind)
    if kind == "roll":  # one amplitude for both groups: the least-squares one
        a_p = a_y = float(np.clip((len(zp) * a_p + len(zy) * a_y) / len(z), p_lo, p_hi))
    a_p, a_y = float(np.clip(a_p, p_lo, p_hi)), float(np.clip(a_y, y_lo, y_hi))
    return GaitEquation(a_pitch=a_p, a_yaw=a_y, nu_pitch=nu_p, nu_yaw=nu_y, delta=delta, frequency=frequency)


@functools.lru_cache(maxsize=64)
def _library_templates(kind: str, robot: Robot) -> tuple[np.ndarray, dict[float, np.ndarray]]:
    """The library gait's pitch template and its yaw template per direction (+1; -1 for an
    undulation's backward wave), complex (N,): ``_fit_library``'s constants, made once a kind and
    robot."""
    base = library_gait(kind, robot)
    modules, pitch_joints = layout(robot)
    k = modules.astype(float)
    pitch = np.where(pitch_joints, base.a_pitch * np.exp(1j * base.nu_pitch * k), 0)
    signs = (1.0, -1.0) if kind == "undulate" else (1.0,)
    yaws = {
        sign: np.where(pitch_joints, 0, base.a_yaw * np.exp(1j * sign * base.nu_yaw * k)) for sign in signs
    }
    return _frozen(pitch), {sign: _frozen(yaw) for sign, yaw in yaws.items()}


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a``, read-only: a cached constant that no caller may change."""
    a.flags.writeable = False
    return a


def _fit_library(
    kind: str, c: np.ndarray, frequency: float, cfg: StructuredConfig, robot: Robot
) -> GaitEquation:
    """The library family's ``kind`` wave at ``frequency`` closest to coefficients c (N,) complex at
    its bin: the library gait's pitch and yaw templates, the yaw one forward or backward
    (undulation), at the offset that fits (free in its drawn range and that range + pi where
    ``library_offsets`` names the kind, else the gait's own or + pi), and the least-squares scale
    in ``amplitude_scale``. Closed forms throughout: a member projects onto itself to rounding."""
    base = library_gait(kind, robot)
    z = c * 1j  # A e^{i phi_k} (``_fit_wave``)
    pitch, yaws = _library_templates(kind, robot)
    lo, hi = cfg.amplitude_scale
    best: tuple[float, float, float, float] | None = None  # residual, scale, direction, offset
    for sign, yaw in yaws.items():
        if kind in cfg.library_offsets:
            found = float(np.angle((z * np.conj(yaw)).sum()))
            ranges = [cfg.library_offsets[kind], tuple(np.add(cfg.library_offsets[kind], np.pi))]
            deltas = [_nearest_in(found, r) for r in ranges]
        else:
            deltas = [base.delta, base.delta + np.pi]
        for delta in deltas:
            template = pitch + yaw * np.exp(1j * delta)
            s = float(np.clip((np.conj(template) * z).sum().real / (np.abs(template) ** 2).sum(), lo, hi))
            r = float(np.linalg.norm(z - s * template))
            if best is None or r < best[0] - 1e-12:
                best = (r, s, sign, delta)
    _, s, sign, delta = best
    return base.scaled(s).model_copy(
        update={
            "nu_yaw": sign * base.nu_yaw,
            "delta": float(np.angle(np.exp(1j * delta))),
            "frequency": frequency,
        }
    )


def _nearest_in(angle: float, bounds: tuple[float, float]) -> float:
    """The angle in [lo, hi] (rad) nearest to ``angle`` on the circle."""
    lo, hi = bounds
    a = lo + (angle - lo) % (2 * np.pi)  # the same angle in [lo, lo + 2 pi)
    if a <= hi:
        return float(a)
    return lo if (lo + 2 * np.pi - a) <= (a - hi) else hi


def _steering(c0: np.ndarray, cfg: StructuredConfig, yaw: np.ndarray) -> tuple[float, float]:
    """The steering wave (amplitude, phase) closest to the yaw joints' (``yaw``) lowest-bin
    coefficients: their mean, its amplitude snapped to the family's {0} u [lo, hi]."""
    if cfg.steering <= 0:
        return 0.0, 0.0
    s = c0[yaw].mean()
    lo, hi = cfg.steering_amplitude
    amplitude = float(abs(s))
    if amplitude < lo / 2:
        return 0.0, 0.0
    return float(np.clip(amplitude, lo, hi)), float(np.angle(s))


@functools.lru_cache(maxsize=64)
def _curve_template(frequency: float, b: int, mirrored: bool, robot: Robot) -> np.ndarray:
    """The unit curving wave's coefficients (N,) complex at its bin b (``_curve``'s constants)."""
    t = curve_wave(1.0, frequency, mirrored, robot).shape(robot)
    return _frozen(t[:, b, 0] + 1j * t[:, b, 1])


def _curve(c: np.ndarray, wave: GaitEquation, cfg: StructuredConfig, robot: Robot) -> GaitEquation | None:
    """The curving wave (``curve_wave``) closest to coefficients c (N, L) complex beside the
    undulation ``wave``: as tuned or mirrored, whichever fits, at the least-squares scale snapped to
    the family's {0} u [lo, hi] times the undulation's scale; None where the family does not curve
    there."""
    if cfg.curve <= 0 or abs(wave.frequency - cfg.curve_frequency) < 1e-6:
        return None
    b = int(np.argmin(np.abs(FREQS - cfg.curve_frequency)))
    lo, hi = np.multiply(cfg.curve_scale, undulation_scale(wave, robot))
    best: tuple[float, bool] = (-np.inf, False)
    for mirrored in (False, True):
        t = _curve_template(cfg.curve_frequency, b, mirrored, robot)
        s = float((np.conj(t) * c[:, b]).sum().real / (np.abs(t) ** 2).sum())
        if s > best[0]:
            best = (s, mirrored)
    s, mirrored = best
    if s < lo / 2:
        return None
    return curve_wave(float(np.clip(s, lo, hi)), cfg.curve_frequency, mirrored, robot)


def _within_limit(member: Member, robot: Robot) -> tuple[Member, np.ndarray]:
    """The member scaled as ``draw_structured`` scales a draw (its peak command at most the limit),
    and its shape (``Member.shape``)."""
    shape, limit = member.shape(robot), robot.command_limit
    if np.hypot(shape[..., 0], shape[..., 1]).sum(axis=1).max() <= limit:
        return member, shape  # the sum of a joint's amplitudes bounds its peak: no synthesis needed
    peak = float(np.abs(shape_to_commands(shape, limit=np.inf)).max())
    if peak <= limit:
        return member, shape
    member = member.scaled(limit / peak)
    return member, member.shape(robot)


def residual(shape: np.ndarray, member: Member | np.ndarray, robot: Robot) -> float:
    """Relative distance of a commanded shape (N, L, 2) from a member (or the member's shape) on
    ``robot``: ||c - c_m|| / ||c||."""
    shape = np.asarray(shape, np.float64)
    theirs = member if isinstance(member, np.ndarray) else member.shape(robot)
    return float(np.linalg.norm(shape - theirs) / max(np.linalg.norm(shape), 1e-12))


def project(
    shape: np.ndarray,
    cfg: StructuredConfig,
    margin: float = SPECIFIC_MARGIN,
    *,
    robot: Robot,
) -> tuple[Member, float]:
    """The member of family ``cfg`` on ``robot`` closest to a commanded joint shape (N, L, 2) rad,
    and the fit's relative residual (0 for a member: projecting a member gives it back). Of the
    kinds, the most specific one whose fit is within ``margin`` times the best fit's residual
    (``SPECIFIC_MARGIN``; 1: the least residual)."""
    shape = np.asarray(shape, np.float64)
    n = robot.n_joints
    if shape.shape != (n, RECORD.n_components, 2) or not np.isfinite(shape).all():
        raise ValueError(f"a joint shape must be finite ({n}, {RECORD.n_components}, 2)")
    cfg = for_robot(cfg, robot)
    c = shape[..., 0] + 1j * shape[..., 1]  # (N, L)
    amplitude, phase = _steering(c[:, STEERING_BIN], cfg, ~layout(robot)[1])
    fits: list[tuple[float, Member]] = []  # each kind's best, most specific kind first
    weights = dict(zip(KINDS, cfg.kind_weights, strict=True))
    for kind in SPECIFIC_FIRST:
        if weights[kind] <= 0:
            continue
        best: tuple[float, Member] | None = None
        for f in cfg.frequencies[kind]:
            b = int(np.argmin(np.abs(FREQS - f)))
            fit = _fit_library if cfg.library else _fit_wave
            wave = fit(kind, c[:, b], float(FREQS[b]), cfg, robot)
            curve = _curve(c, wave, cfg, robot) if kind == "undulate" else None
            member, theirs = _within_limit(
                Member(kind=kind, wave=wave, steering_amplitude=amplitude, steering_phase=phase, curve=curve),
                robot,
            )
            r = residual(shape, theirs, robot)
            if best is None or r < best[0] - 1e-9:
                best = (r, member)
        if best is not None:
            fits.append(best)
    if not fits:
        raise ValueError("the family allows no kind of wave (every kind weight is 0)")
    least = min(r for r, _ in fits)
    r, member = next(fit for fit in fits if fit[0] <= margin * least + 1e-9)
    return member, r


def project_many(shapes: np.ndarray, cfg: StructuredConfig, robot: Robot) -> tuple[list[Member], np.ndarray]:
    """``project`` over commanded shapes (B, N, L, 2) on ``robot``: the members and residuals (B,)."""
    fits = [project(s, cfg, robot=robot) for s in np.asarray(shapes, np.float64)]
    return [m for m, _ in fits], np.array([r for _, r in fits])
