"""Constant-acceleration Kalman filter for the box centre (pure JAX; ``init`` / ``update`` pair).

State x = (p, v, a) (9,) in the camera frame [m, m/s, m/s^2]; motion model: white jerk of spectral
density ``jerk_psd`` [m^2/s^5] per axis (the discretised Wiener-process-acceleration model, Bar-Shalom,
Li & Kirubarajan, Sec. 6.3.3). Measurement: the refined position p with a full 3x3 covariance R
(from the pose fit, so that the weak depth direction is trusted less).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array


@dataclass(frozen=True)
class FilterConfig:
    """Static parameters of the filter.

    Attributes:
        dt: frame interval [s].
        jerk_psd: spectral density of the white jerk [m^2/s^5].
        init_std: initial standard deviations of (p, v, a) [m, m/s, m/s^2].
    """

    dt: float
    jerk_psd: float = 50.0
    init_std: tuple[float, float, float] = (0.05, 2.0, 20.0)


class FilterState(NamedTuple):
    """Attributes: mean (9,) = (p, v, a); cov (9, 9)."""

    mean: Array
    cov: Array


def transition(config: FilterConfig) -> tuple[Array, Array]:
    """(F, Q) (9, 9) of one frame interval. ``config.jerk_psd`` may be a traced scalar (the
    smoother passes it so); ``config.dt`` is a number.
    """
    if not isinstance(config.jerk_psd, jax.Array):  # a number (Python or NumPy): as before
        f, q = transition_np(config.jerk_psd, config.dt)
        return jnp.asarray(f), jnp.asarray(q)
    # Q is linear in jerk_psd: the same products as transition_np's (the Kronecker factor is 0/1)
    f, q_unit = transition_np(1.0, config.dt)
    return jnp.asarray(f), config.jerk_psd * jnp.asarray(q_unit)


def transition_np(jerk_psd: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, Q) (9, 9) of an interval ``dt`` [s] of any length (NumPy, for use between frames)."""
    f1 = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    q1 = jerk_psd * np.array(
        [
            [dt**5 / 20, dt**4 / 8, dt**3 / 6],
            [dt**4 / 8, dt**3 / 3, dt**2 / 2],
            [dt**3 / 6, dt**2 / 2, dt],
        ]
    )
    eye = np.eye(3)
    return np.kron(f1, eye), np.kron(q1, eye)


def init(config: FilterConfig, position: Array) -> FilterState:
    """State at the first measurement: p measured, v = a = 0 with wide uncertainty."""
    mean = jnp.concatenate([position, jnp.zeros(6, position.dtype)])
    std = jnp.repeat(jnp.asarray(config.init_std, position.dtype), 3)
    return FilterState(mean, jnp.diag(std * std))


def init_np(config: FilterConfig, position: np.ndarray) -> FilterState:
    """:func:`init` in NumPy (on the host between frames: eager JAX operations compile on their
    first use, which cost the real-time eye 0.2 s on the frame that first needed them).
    """
    position = np.asarray(position)
    std = np.repeat(np.asarray(config.init_std, position.dtype), 3)
    return FilterState(np.concatenate([position, np.zeros(6, position.dtype)]), np.diag(std * std))


def predict(config: FilterConfig, state: FilterState) -> FilterState:
    """The state one frame interval ``config.dt`` later (constant-acceleration model)."""
    f, q = transition(config)
    return FilterState(f @ state.mean, f @ state.cov @ f.T + q)


def correct(state: FilterState, position: Array, cov: Array, use: Array) -> FilterState:
    """Measurement update with position (3,) and covariance (3, 3); skipped where ``use`` is False."""
    h = jnp.concatenate([jnp.eye(3), jnp.zeros((3, 6))], axis=1)
    s = h @ state.cov @ h.T + cov
    gain = jnp.linalg.solve(s, h @ state.cov).T  # P H^T S^-1 (S symmetric)
    mean = state.mean + gain @ (position - h @ state.mean)
    ikh = jnp.eye(9) - gain @ h
    new_cov = ikh @ state.cov @ ikh.T + gain @ cov @ gain.T  # Joseph form
    return FilterState(jnp.where(use, mean, state.mean), jnp.where(use, new_cov, state.cov))


def update(
    config: FilterConfig, state: FilterState, position: Array, cov: Array, use: Array
) -> FilterState:
    """Predict one frame ahead, then correct with the measurement (if ``use``)."""
    return correct(predict(config, state), position, cov, use)


def filter_sequence(
    config: FilterConfig, positions: Array, covs: Array, valid: Array
) -> tuple[FilterState, FilterState]:
    """Causal pass over a sequence (one ``lax.scan``): (filtered, predicted) states, stacked (T, ...).

    positions (T, 3) [m], covs (T, 3, 3) [m^2], valid (T,) bool. The filter starts at frame 0 from
    the first valid position with the wide ``init_std``; invalid frames are predictions only.
    """
    first = jnp.argmax(valid)
    state0 = init(config, positions[first])
    f, q = transition(config)
    cov_pred0 = state0.cov

    def step(state, x):
        z, r, use, is_first = x
        pred = FilterState(f @ state.mean, f @ state.cov @ f.T + q)
        pred = jax.tree.map(lambda a, b: jnp.where(is_first, a, b), state, pred)
        new = correct(pred, z, r, use)
        return new, (new, pred)

    idx = jnp.arange(positions.shape[0])
    safe_pos = jnp.where(valid[:, None], positions, positions[first])
    safe_cov = jnp.where(valid[:, None, None], covs, jnp.eye(3))
    _, (filt, pred) = jax.lax.scan(step, state0, (safe_pos, safe_cov, valid, idx == 0))
    del cov_pred0
    return filt, pred


def rts_smooth(config: FilterConfig, filtered: FilterState, predicted: FilterState) -> FilterState:
    """Rauch-Tung-Striebel smoother over the output of :func:`filter_sequence` (offline; (T, ...))."""
    f, _ = transition(config)

    def step(nxt, x):
        filt_mean, filt_cov, pred_mean, pred_cov = x
        gain = jnp.linalg.solve(pred_cov, f @ filt_cov).T  # P_k F^T P_{k+1|k}^-1
        mean = filt_mean + gain @ (nxt.mean - pred_mean)
        cov = filt_cov + gain @ (nxt.cov - pred_cov) @ gain.T
        out = FilterState(mean, 0.5 * (cov + cov.T))
        return out, out

    last = jax.tree.map(lambda a: a[-1], filtered)
    xs = (filtered.mean[:-1], filtered.cov[:-1], predicted.mean[1:], predicted.cov[1:])
    _, smoothed = jax.lax.scan(step, last, xs, reverse=True)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), smoothed, last)


def maneuver_reset(
    config: FilterConfig,
    previous: FilterState,
    predicted: FilterState,
    position: Array,
    cov: Array,
    nis_threshold: float,
) -> tuple[FilterState, Array]:
    """Impact (manoeuvre) detection and restart of the filter's motion state.

    A constant-acceleration model cannot follow an impact (a jump of velocity): the innovation
    nu = p - p_pred is then far outside its covariance S = P_pp + R. Where the normalised innovation
    squared nu^T S^-1 nu exceeds ``nis_threshold`` (chi-square, 3 dof: 16.3 for p = 0.001) the
    state restarts from the measurement: p measured, v the finite difference from the previous
    filtered position over one frame, a = 0, with the covariances of that difference
    (var v = (P_pp,prev + R) / dt^2) and the wide initial acceleration uncertainty.

    Returns (restarted state, detected) where ``detected`` is a bool scalar; the caller selects.
    """
    dt = config.dt
    nu = position - predicted.mean[:3]
    s = predicted.cov[:3, :3] + cov
    nis = nu @ jnp.linalg.solve(s, nu)
    p_prev = previous.mean[:3]
    v = (position - p_prev) / dt  # only where the caller accepted the fit (gated)
    var_v = (previous.cov[:3, :3] + cov) / dt**2
    a_std = config.init_std[2]
    z = jnp.zeros((3, 3), position.dtype)
    restarted_cov = jnp.block(
        [
            [cov, cov / dt, z],
            [cov / dt, var_v, z],
            [z, z, a_std**2 * jnp.eye(3, dtype=position.dtype)],
        ]
    )
    mean = jnp.concatenate([position, v, jnp.zeros(3, position.dtype)])
    return FilterState(mean, restarted_cov), nis > nis_threshold
