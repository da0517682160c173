"""Topological joint shape (paper 3.2.1) and its inverse: the one place the FFT convention lives.

Convention: for a record x(n), n = 0..T-1 at ``sample_rate``, the coefficient of excited bin b_l is
c_l = 2 X[b_l] / T with X = numpy.fft.rfft(x). |c_l| is then the amplitude (rad) of that sinusoid and
x(t) = sum_l Re(c_l exp(i 2 pi f_l t)) for a signal made only of the excited components. A shape
stores c as (real, imag) in its last axis: shape (..., N, L, 2) for N joints.
"""

from __future__ import annotations

import functools

import numpy as np

from snakeloco.sim.gaits.excitation import RECORD, ExcitationConfig
from snakeloco.sim.robot.description import COMMAND_LIMIT


def joint_shape(angles: np.ndarray, cfg: ExcitationConfig = RECORD) -> np.ndarray:
    """Single-sided spectrum of joint signals at the excited bins.

    Args:
        angles: (..., T, N) joint angles or commands (rad) at ``cfg.sample_rate``, N joints.
        cfg: the excitation whose bins to keep.

    Returns:
        (..., N, L, 2) float64: real and imaginary parts of c_kl (rad).
    """
    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim < 2 or angles.shape[-2] != cfg.n_samples or angles.shape[-1] < 1:
        raise ValueError(f"expected (..., {cfg.n_samples}, N) angles, got {angles.shape}")
    spectrum = np.fft.rfft(angles, axis=-2)  # (..., T//2+1, 8)
    c = 2.0 * spectrum[..., cfg.bins, :] / cfg.n_samples  # (..., L, 8)
    c = np.swapaxes(c, -1, -2)  # (..., 8, L)
    return np.stack([c.real, c.imag], axis=-1)  # (..., 8, L, 2)


def synthesis_phase(
    freqs: np.ndarray,
    *,
    n_samples: int = RECORD.n_samples,
    sample_rate: float = RECORD.sample_rate,
    stride: int = 1,
) -> np.ndarray:
    """Phases 2 pi f_l t_n of the inverse transform at t_n = n / sample_rate, n = 0, stride, ... < T.

    The frequencies are snapped to the record's FFT grid: float32 round-off in stored frequencies
    would otherwise grow into a phase error of 2 pi t df over the 100 s record. With these phases a
    joint signal is x(t_n) = sum_l (re_l cos - im_l sin); ``stride`` = ``sim.BODY_DOWNSAMPLE`` gives
    the body series' time stamps (the model's body decoder uses that).

    Returns:
        (ceil(T / stride), L) float64 radians.
    """
    freqs = np.asarray(freqs, dtype=np.float64)
    bins = freqs * n_samples / sample_rate
    if np.abs(bins - np.round(bins)).max() > 1e-3:
        raise ValueError(
            f"frequencies {freqs.tolist()} Hz are not on the {sample_rate / n_samples} Hz FFT grid"
        )
    n = np.arange(0, n_samples, stride)  # (T',)
    return 2.0 * np.pi * np.outer(n, np.round(bins)) / n_samples


def shape_to_commands(
    shape: np.ndarray,
    freqs: np.ndarray | None = None,
    *,
    n_samples: int = RECORD.n_samples,
    sample_rate: float = RECORD.sample_rate,
    limit: float = COMMAND_LIMIT,
    response: np.ndarray | None = None,
) -> np.ndarray:
    """Resynthesise joint commands from a joint shape by inverse FFT (the inverse of ``joint_shape``).

    u_k(t_n) = sum_l Re(c_kl exp(i 2 pi f_l t_n)), t_n = n / sample_rate, clipped to +/- ``limit`` rad.

    With ``response`` (the servo's measured/commanded complex gain per joint and frequency, see
    ``servo_response``), each c_kl is first divided by it: the shape is then read as the *measured*
    joint motion wanted, and the commands are those that make the servos produce it (servo-lag
    compensation; the learned shapes are measured angles).

    Args:
        shape: (..., N, L, 2) real and imaginary parts of c_kl (rad), N joints.
        freqs: (L,) frequencies of the components (Hz); default: the standard excitation's.
        n_samples: samples to synthesise (T).
        sample_rate: command rate (Hz).
        limit: clip bound (rad).

    Returns:
        (..., T, N) float64 commands (rad).
    """
    shape = np.asarray(shape, dtype=np.float64)
    freqs = RECORD.freqs if freqs is None else np.asarray(freqs, dtype=np.float64)
    if shape.ndim < 3 or shape.shape[-2:] != (freqs.shape[0], 2):
        raise ValueError(f"expected (..., N, {freqs.shape[0]}, 2) shape, got {shape.shape}")
    n_joints = shape.shape[-3]
    if response is not None:
        response = np.asarray(response, dtype=np.float64)
        if response.shape != (n_joints, freqs.shape[0], 2):
            raise ValueError(f"response must be ({n_joints}, {freqs.shape[0]}, 2), got {response.shape}")
        c = (shape[..., 0] + 1j * shape[..., 1]) / (response[..., 0] + 1j * response[..., 1])
        shape = np.stack([c.real, c.imag], axis=-1)
    cos, sin = _synthesis_basis(tuple(freqs.tolist()), n_samples, float(sample_rate))
    # Re(c e^{i w t}) = re cos(w t) - im sin(w t); contract over L for every joint.
    commands = cos @ np.swapaxes(shape[..., 0], -1, -2) - sin @ np.swapaxes(
        shape[..., 1], -1, -2
    )  # (..., T, 8)
    return np.clip(commands, -limit, limit)


@functools.lru_cache(maxsize=16)
def _synthesis_basis(
    freqs: tuple[float, ...], n_samples: int, sample_rate: float
) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin (T, L) of ``synthesis_phase``, read-only: the same values every call, computed once
    (they were a third of a designer decode's command synthesis)."""
    arg = synthesis_phase(np.asarray(freqs), n_samples=n_samples, sample_rate=sample_rate)
    cos, sin = np.cos(arg), np.sin(arg)
    cos.flags.writeable = sin.flags.writeable = False
    return cos, sin


MIN_EXCITATION = 1e-3
"""Smallest commanded coefficient (rad) at which a record's measured/commanded ratio is counted."""


def servo_response(
    commands: np.ndarray,
    joint_angles: np.ndarray,
    cfg: ExcitationConfig = RECORD,
    chunk: int = 256,
) -> np.ndarray:
    """Mean complex gain measured/commanded of each joint at each excited frequency.

    Args:
        commands, joint_angles: (n, T, N) records (rad): arrays, or ``Dataset.rows`` read a chunk at a
            time.

    A record counts at a joint and frequency only where it commands at least ``MIN_EXCITATION`` there
    (every paper-family record does at every bin; a structured gait only at its own one or two): the
    mean is over those records, and a joint and frequency no record excites keeps gain 1.

    Returns:
        (N, L, 2) real and imaginary parts of mean_n (X_meas / X_cmd): |G| is the amplitude ratio,
        arg G the phase lag.
    """
    n_joints = np.asarray(commands[0:1]).shape[-1]  # an array or ``Dataset.rows``
    total = np.zeros((n_joints, len(cfg.bins)), dtype=np.complex128)
    count = np.zeros((n_joints, len(cfg.bins)), dtype=np.int64)
    for i in range(0, len(commands), chunk):
        u = joint_shape(np.asarray(commands[i : i + chunk], np.float64), cfg)
        q = joint_shape(np.asarray(joint_angles[i : i + chunk], np.float64), cfg)
        cu, cq = u[..., 0] + 1j * u[..., 1], q[..., 0] + 1j * q[..., 1]
        excited = np.abs(cu) > MIN_EXCITATION
        total += np.where(excited, cq / np.where(excited, cu, 1.0), 0.0).sum(axis=0)
        count += excited.sum(axis=0)
    g = np.where(count > 0, total / np.maximum(count, 1), 1.0 + 0.0j)
    return np.stack([g.real, g.imag], axis=-1)
