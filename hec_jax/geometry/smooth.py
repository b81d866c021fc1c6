"""Offline smoothing of a tracked pose sequence (pure JAX; one ``jit`` per sequence length).

The per-frame fits of :mod:`track` are measurements (R_i, t_i) with an information matrix
Lambda_i (6, 6) over the pose increment (dw, dt) (left perturbation, ``refine.retract``). For a
nearly frontal cube the tilt is weakly observed in one frame (the side faces are a few px wide),
and a tilt error moves the fitted centre sideways; both are fixed by using the whole sequence:

1. rotations: Gauss-Newton on the marginal rotation information of every frame
   (Lambda_ww - Lambda_wt Lambda_tt^-1 Lambda_tw) plus a white-angular-acceleration prior, the
   second difference of the rotation, log(R_{i+2} R_{i+1}^T) - log(R_{i+1} R_i^T), with variance
   (2/3) q_w dt^3 per axis (q_w the spectral density, [rad^2/s^3]). Any motion, no model of the
   pendulum.
2. centres: each frame's centre conditioned on its smoothed rotation,
   t_i - Lambda_tt^-1 Lambda_tw log(R*_i R_i^T), covariance Lambda_tt^-1, then the
   constant-acceleration Kalman filter and the Rauch-Tung-Striebel smoother (:mod:`filter`).

Frames without a measurement get zero information (bridged by the priors).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from hec_jax.geometry import filter as kf
from hec_jax.geometry.refine import so3_exp, so3_log


@dataclass(frozen=True)
class SmootherConfig:
    """Static parameters of the smoother.

    Attributes:
        angular_accel_psd: spectral density of the white angular acceleration [rad^2/s^3].
        jerk_psd: spectral density of the white jerk of the centre [m^2/s^5].
        info_scale: factor on the per-frame information [-]. The edge points of one edge share
            their error (blur, a bias along the whole edge), so J^T W J / s^2 over-counts them:
            on a held-out rendered swing (release 0.35 rad, not the benchmark's) the per-frame
            errors were 2-7x the predicted standard deviations (NEES median 670 against 6);
            0.03 was chosen there from {1, 0.3, 0.1, 0.03, 0.01}. Later (denser edge points) 0.01
            with ``jerk_psd`` 10 (was 50) on two held-out swings (release 0.35 and 0.58 rad):
            acceleration RMS 0.27, 0.40 -> 0.13, 0.23 m/s^2, from jerk_psd {5 .. 100} x
            info_scale {0.003 .. 0.1}; lower values smooth more and would blur faster motion.
        iters: Gauss-Newton iterations of the rotation pass.
    """

    angular_accel_psd: float = 20.0
    jerk_psd: float = 10.0
    info_scale: float = 0.01
    iters: int = 3


class SmoothedTrack(NamedTuple):
    """Attributes: rotation (T, 3, 3) R_cam_box; position, velocity, acceleration (T, 3)
    [m, m/s, m/s^2]; position_cov (T, 3, 3) [m^2]."""

    rotation: Array
    position: Array
    velocity: Array
    acceleration: Array
    position_cov: Array


def _split(info: Array) -> tuple[Array, Array, Array]:
    """(marginal rotation information (3, 3), Lambda_tt^-1 (3, 3), Lambda_tt^-1 Lambda_tw (3, 3))."""
    lww, lwt, ltt = info[:3, :3], info[:3, 3:], info[3:, 3:]
    ltt_inv = jnp.linalg.inv(ltt + 1e-12 * jnp.eye(3))
    cond = ltt_inv @ lwt.T
    marg = lww - lwt @ cond
    return 0.5 * (marg + marg.T), 0.5 * (ltt_inv + ltt_inv.T), cond


def smooth_rotations(rotations: Array, info_rot: Array, dt: float, cfg: SmootherConfig) -> Array:
    """Rotation pass: (T, 3, 3) measured rotations, (T, 3, 3) their information [1/rad^2]."""
    t_n = rotations.shape[0]
    sigma = jnp.sqrt(2.0 / 3.0 * cfg.angular_accel_psd * dt**3)  # [rad]
    # L^T with L L^T = information (eigen square root: zero rows where unmeasured)
    evals, evecs = jnp.linalg.eigh(info_rot)
    sqrt_info = jnp.sqrt(jnp.clip(evals, 0.0, None))[..., :, None] * jnp.swapaxes(evecs, -1, -2)

    def residuals(delta, nominal):
        r = so3_exp(delta.reshape(t_n, 3)) @ nominal
        meas = jnp.einsum("tij,tj->ti", sqrt_info, so3_log(r @ jnp.swapaxes(rotations, -1, -2)))
        omega = so3_log(r[1:] @ jnp.swapaxes(r[:-1], -1, -2))
        return jnp.concatenate([meas.reshape(-1), ((omega[1:] - omega[:-1]) / sigma).reshape(-1)])

    def step(nominal, _):
        zero = jnp.zeros(3 * t_n, rotations.dtype)
        res = residuals(zero, nominal)
        jac = jax.jacfwd(residuals)(zero, nominal)
        h = jac.T @ jac + 1e-9 * jnp.eye(3 * t_n)
        delta = -jnp.linalg.solve(h, jac.T @ res)
        return so3_exp(delta.reshape(t_n, 3)) @ nominal, None

    out, _ = jax.lax.scan(step, rotations, None, cfg.iters)
    return out


def _smooth(rotations, positions, information, valid, dt, cfg: SmootherConfig):
    info = jnp.where(valid[:, None, None], cfg.info_scale * information, 0.0)
    marg, ltt_inv, cond = jax.vmap(_split)(info)
    rot = smooth_rotations(rotations, marg, dt, cfg)
    shift = so3_log(rot @ jnp.swapaxes(rotations, -1, -2))
    pos = positions - jnp.einsum("tij,tj->ti", cond, shift)
    fcfg = kf.FilterConfig(dt=dt, jerk_psd=cfg.jerk_psd)
    filt, pred = kf.filter_sequence(fcfg, pos, ltt_inv, valid)
    sm = kf.rts_smooth(fcfg, filt, pred)
    m = sm.mean
    return SmoothedTrack(rot, m[:, :3], m[:, 3:6], m[:, 6:], sm.cov[:, :3, :3])


_JIT: dict = {}
PAD = 32  # sequence lengths are padded to a multiple of this (one compilation per size)


def smooth_track(
    rotations, positions, information, valid, dt: float, cfg: SmootherConfig = SmootherConfig()
) -> SmoothedTrack:
    """Smooth a tracked sequence (NumPy in and out). Needs >= 4 valid frames, else returns the
    inputs unchanged with zero velocity and acceleration.

    Args:
        rotations: (T, 3, 3) per-frame R_cam_box (a guess where not valid, e.g. coasted).
        positions: (T, 3) per-frame centres [m] (any finite value where not valid).
        information: (T, 6, 6) information of (dw, dt) [1/rad^2, 1/m^2].
        valid: (T,) bool.
        dt: frame interval [s].
    """
    valid = np.asarray(valid, bool)
    t_n = len(valid)
    positions = np.where(valid[:, None], positions, 0.0)
    if valid.sum() < 4:
        z = np.zeros((t_n, 3))
        return SmoothedTrack(
            np.asarray(rotations), positions, z, z, np.tile(np.eye(3), (t_n, 1, 1))
        )
    key = (cfg, float(dt))
    if key not in _JIT:
        _JIT[key] = jax.jit(lambda r, p, i, v: _smooth(r, p, i, v, dt, cfg))
    # pad to a multiple of PAD frames (unmeasured: only the priors act there) to share compilations
    n = -(-t_n // PAD) * PAD
    pad = n - t_n

    def ext(x, fill):
        x = np.asarray(x, np.float64)
        return np.concatenate([x, np.repeat(fill, pad, axis=0)]) if pad else x

    out = _JIT[key](
        ext(rotations, np.asarray(rotations)[-1:]),
        ext(positions, np.zeros((1, 3))),
        ext(information, np.zeros((1, 6, 6))),
        np.concatenate([valid, np.zeros(pad, bool)]),
    )
    return SmoothedTrack(*(np.asarray(x)[:t_n] for x in out))
