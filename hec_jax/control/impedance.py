"""Impedance control of Sec. 4.1 with the virtual force of Sec. 4.2 (Eqs. 40-44, 48).

Reading implemented (docs/paper_readings.md, Sec. 2, dots restored):

    tau = tau_eff + tau_comp + tau_null                                              (Eq. 41 + null)
    tau_eff  = J^T { M_x [ M_e^-1 (-K_e dX - B_e dX' + F_o) + X_d'' - J' theta' ]
                     - (I - M_x M_e^-1) F_int }                                       (Eq. 42)
    tau_comp = (M^-1 J^T M_x J)^T h = J^T M_x J M^-1 h                                (Eq. 43)
    M_x      = (J M^-1 J^T)^-1                                                       (Eq. 44)

With M theta'' + h = tau + J^T F_int (Eq. 39) this gives, for the task coordinates,
M_e dX'' + B_e dX' + K_e dX = F_int + F_o (Eq. 48) exactly (dX = X_e - X_d, X_d'' included).

Redundancy (3 joints, 2-D task): Eq. 43 compensates h only in the task space. We compensate h fully
by adding the null-space part of h and a posture PD term, both through Khatib's dynamically
consistent projector N^T = I - J^T Jbar^T, Jbar = M^-1 J^T M_x:

    tau_null = N^T [ h + M ( -K_n (theta - theta_0) - D_n theta' ) ],

so that J M^-1 tau_null = 0 and the task dynamics stay Eq. 48 while the self-motion is a damped
posture regulator. Gains are diagonal (per task axis) and positive.

M_x is computed with a damped inverse of Lambda^-1 = J M^-1 J^T (eigen-decomposition, eigenvalues
s -> s / (s^2 + lambda^2)); its condition number is reported in ``ControlInfo``. Accelerations that
the control law needs but cannot measure (X_e'' and X_o'' for F_o) are backward differences of the
measured velocities over one control period (one sample old), as a real controller would have.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.control.virtual import (
    SphereKinematics,
    VirtualParams,
    sphere_kinematics,
    virtual_force,
)


class TaskObs(NamedTuple):
    """Everything the controller reads at one step (task coordinates (x, z), world frame).

    Attributes:
        q: [rad] (3,) arm joint angles theta.
        qd: [rad/s] (3,) joint velocities theta'.
        M: [kg m^2] (3, 3) joint-space inertia M(theta) (armature included).
        h: [N m] (3,) h(theta, theta') of Eq. 39: Coriolis, centrifugal, gravity and joint damping.
        x_e: [m] (2,) end-effector position X_e.
        xd_e: [m/s] (2,) end-effector velocity X_e' = J theta'.
        J: [m/rad] (2, 3) Jacobian dX_e/dtheta.
        jdot_qdot: [m/s^2] (2,) J' theta'.
        f_int: [N] (2,) interaction force exerted ON the end-effector by the environment (Eq. 39).
        x_o: [m] (2,) object position X_o (cube centre).
        xd_o: [m/s] (2,) object velocity X_o'.
        xdd_o: [m/s^2] (2,) object acceleration X_o'' when an estimator provides one (e.g. the
            eye's filter); ``None`` (default): the controller differentiates ``xd_o`` over one sample.
    """

    q: jax.Array
    qd: jax.Array
    M: jax.Array
    h: jax.Array
    x_e: jax.Array
    xd_e: jax.Array
    J: jax.Array
    jdot_qdot: jax.Array
    f_int: jax.Array
    x_o: jax.Array
    xd_o: jax.Array
    xdd_o: jax.Array | None = None


class ImpedanceParams(NamedTuple):
    """Target impedance of Eq. 40, diagonal per task axis (pytree leaves).

    Attributes:
        m_e: [kg] (2,) desired inertia M_e (> 0).
        b_e: [N s/m] (2,) desired viscosity B_e (> 0).
        k_e: [N/m] (2,) desired stiffness K_e (>= 0).
    """

    m_e: jax.Array
    b_e: jax.Array
    k_e: jax.Array


def impedance_params(m_e, b_e, k_e) -> ImpedanceParams:
    """Validated ImpedanceParams (host side): scalars or (2,) diagonals.

    Requires M_e > 0, B_e > 0, K_e >= 0 (ValueError otherwise).
    """
    out = []
    for name, v, strict in (("m_e", m_e, True), ("b_e", b_e, True), ("k_e", k_e, False)):
        a = np.asarray(v, dtype=float)
        if a.ndim > 1 or (a.ndim == 1 and a.shape[0] != 2):
            raise ValueError(f"{name} must be a scalar or shape (2,), got shape {a.shape}")
        a = np.broadcast_to(a, (2,)).copy()
        bad = ~np.isfinite(a) | ((a <= 0) if strict else (a < 0))
        if np.any(bad):
            raise ValueError(f"{name} must be finite and {'> 0' if strict else '>= 0'}, got {a}")
        out.append(jnp.asarray(a))
    return ImpedanceParams(*out)


class Target(NamedTuple):
    """Desired end-effector motion X_d and its derivatives [m], [m/s], [m/s^2] (2,) each."""

    x_d: jax.Array
    xd_d: jax.Array
    xdd_d: jax.Array


def fixed_target(x_d) -> Target:
    """A resting equilibrium X_d (2,) [m]."""
    x_d = jnp.asarray(x_d, dtype=float)
    if x_d.shape != (2,):
        raise ValueError(f"x_d must have shape (2,), got {x_d.shape}")
    return Target(x_d=x_d, xd_d=jnp.zeros(2), xdd_d=jnp.zeros(2))


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """Static settings of the impedance controller (hashable).

    The control period and the torque limits are the plant's (read from the model: see
    :func:`make_impedance_controller`), not settings.

    Attributes:
        mx_damping: [1/kg] lambda of the damped inverse in Eq. 44.
        null_kp: [1/s^2] posture stiffness K_n (scaled by M, i.e. an acceleration gain).
        null_kd: [1/s] posture damping D_n.
    """

    mx_damping: float = 1e-3
    null_kp: float = 25.0
    null_kd: float = 10.0

    def __post_init__(self):
        if not self.mx_damping >= 0:
            raise ValueError(f"mx_damping must be >= 0, got {self.mx_damping}")
        if self.null_kp < 0 or self.null_kd < 0:
            raise ValueError("null-space gains must be >= 0")


DEFAULT_CONFIG = ControllerConfig()


def solve_spd(A: jax.Array, B: jax.Array) -> jax.Array:
    """A^-1 B for a small symmetric positive definite A (n, n), B (n, k), n static.

    Cholesky factorisation A = L L^T and the two triangular solves, unrolled over the (static)
    entries: elementwise arithmetic only, so that under ``vmap`` on a GPU it is one fused kernel
    instead of a batched LU factorisation and solves (library calls); ``jit``, ``vmap`` and
    ``grad`` go through it. Only the lower triangle of A is read. Meant for the arm's 3 x 3
    joint-space inertia M(theta) (SPD: armature on every joint); an A that is not positive definite
    gives NaN, as a singular matrix gives inf/NaN in ``jnp.linalg.solve``.
    """
    n = A.shape[-1]
    if A.ndim != 2 or A.shape != (n, n) or B.ndim < 1 or B.shape[0] != n:
        raise ValueError(f"need A (n, n) and B (n, ...), got {A.shape} and {B.shape}")
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        L[j][j] = jnp.sqrt(A[j, j] - sum(L[j][k] * L[j][k] for k in range(j)))
        for i in range(j + 1, n):
            L[i][j] = (A[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    y = []  # L y = B
    for i in range(n):
        y.append((B[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x = [None] * n  # L^T x = y
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return jnp.stack(x)


def operational_inertia(M: jax.Array, J: jax.Array, damping: float) -> tuple[jax.Array, jax.Array]:
    """Eq. 44, M_x = (J M^-1 J^T)^-1 [kg] (2, 2), with a damped inverse; also its condition number.

    Lambda^-1 = J M^-1 J^T = A = V diag(s) V^T (2 x 2, symmetric positive semi-definite); the
    damped inverse is M_x = V diag(s / (s^2 + lambda^2)) V^T = A (A^2 + lambda^2 I)^-1, equal to
    the exact inverse up to a relative lambda^2/s^2. For a 2 x 2 matrix it is computed in closed
    form from the invariants t = s1 + s2 = tr A and p = s1 s2 = det A (Cayley-Hamilton):

        M_x = alpha I + beta A,  alpha = p t / D,  beta = (lambda^2 - p) / D,
        D = (s1^2 + lambda^2)(s2^2 + lambda^2) = p^2 + lambda^2 (t^2 - 2 p) + lambda^4,

    (at lambda = 0: (t I - A) / p = A^-1). No eigendecomposition: smooth in A for lambda > 0, also
    where s1 = s2 (there the derivative of an eigendecomposition is singular), and on a GPU one
    fused elementwise kernel instead of a batched ``eigh``. p is clamped at 0 (A is PSD up to
    rounding). cond = s_max / s_min = s_max^2 / p (inf at a singularity). M^-1 J^T comes from
    :func:`solve_spd` (unrolled Cholesky, no batched LU on a GPU).
    """
    A = J @ solve_spd(M, J.T)
    A = 0.5 * (A + A.T)
    a, b, d = A[0, 0], A[0, 1], A[1, 1]
    t = a + d  # [1/kg]
    p = jnp.maximum(a * d - b * b, 0.0)  # [1/kg^2]
    lam2 = damping**2
    D = p * p + lam2 * (t * t - 2.0 * p) + lam2 * lam2
    M_x = (p * t / D) * jnp.eye(2, dtype=A.dtype) + ((lam2 - p) / D) * A
    # condition number from the eigenvalues s_max = t/2 + r, s_min = p / s_max (no cancellation)
    q = (0.5 * (a - d)) ** 2 + b * b
    r = jnp.where(q > 0, jnp.sqrt(jnp.where(q > 0, q, 1.0)), 0.0)  # NaN-free derivative at q = 0
    s_max = 0.5 * t + r
    cond = jnp.where(p > 0, s_max * s_max / jnp.where(p > 0, p, 1.0), jnp.inf)
    return M_x, cond


class ControlInfo(NamedTuple):
    """Diagnostics of one control step.

    Attributes:
        tau_cmd: [N m] (3,) torque before saturation.
        f_o: [N] (2,) virtual force F_o (Eq. 47).
        mx_cond: () condition number of J M^-1 J^T.
        saturated: () bool, any joint at its torque limit, or a commanded torque not finite
            (only with ``mx_damping`` = 0 at a singular Jacobian, where ``mx_cond`` is inf).
        sphere: the virtual-sphere kinematics (Eqs. 45-46).
        xdd_e: [m/s^2] (2,) the hand acceleration used for dX_o'' (backward difference).
    """

    tau_cmd: jax.Array
    f_o: jax.Array
    mx_cond: jax.Array
    saturated: jax.Array
    sphere: SphereKinematics
    xdd_e: jax.Array


def impedance_torque(
    obs: TaskObs,
    params: ImpedanceParams,
    target: Target,
    f_o: jax.Array,
    q_posture: jax.Array,
    cfg: ControllerConfig,
) -> tuple[jax.Array, jax.Array]:
    """Eqs. 41-44 plus the null-space term; returns (tau [N m] (3,), cond(J M^-1 J^T)).

    All vectors in task coordinates (x, z) of the world frame; F_int and F_o are forces ON the hand.
    """
    M, J, h = obs.M, obs.J, obs.h
    M_x, cond = operational_inertia(M, J, cfg.mx_damping)
    inv_m_e = 1.0 / jnp.where(params.m_e > 0, params.m_e, jnp.inf)  # NaN-safe: 0 if M_e <= 0
    dX = obs.x_e - target.x_d  # [m]
    dXd = obs.xd_e - target.xd_d  # [m/s]
    # Eq. 42 (with F_o of Eq. 48): desired task acceleration [m/s^2] minus J' theta'
    acc = inv_m_e * (-params.k_e * dX - params.b_e * dXd + f_o) + target.xdd_d - obs.jdot_qdot
    f_int_term = obs.f_int - M_x @ (inv_m_e * obs.f_int)  # (I - M_x M_e^-1) F_int [N]
    tau_eff = J.T @ (M_x @ acc - f_int_term)
    # Eq. 43: J^T M_x J M^-1 h = J^T Jbar^T h, Jbar = M^-1 J^T M_x (dynamically consistent inverse)
    Jbar = solve_spd(M, J.T) @ M_x  # (3, 2)
    tau_comp = J.T @ (Jbar.T @ h)
    # null space: rest of h and posture PD, projected by N^T = I - J^T Jbar^T
    tau_0 = h + M @ (-cfg.null_kp * (obs.q - q_posture) - cfg.null_kd * obs.qd)
    tau_null = tau_0 - J.T @ (Jbar.T @ tau_0)
    return tau_eff + tau_comp + tau_null, cond


class ControllerState(NamedTuple):
    """Memory of the controller.

    Attributes:
        q_posture: [rad] (3,) null-space posture theta_0 (the posture at ``init``).
        xd_e_prev: [m/s] (2,) hand velocity at the previous step.
        xd_o_prev: [m/s] (2,) object velocity at the previous step.
    """

    q_posture: jax.Array
    xd_e_prev: jax.Array
    xd_o_prev: jax.Array


Init = Callable[[TaskObs], ControllerState]
Apply = Callable[
    [ImpedanceParams, VirtualParams, Target, ControllerState, TaskObs],
    tuple[jax.Array, ControllerState, ControlInfo],
]


def _check_obs_shapes(obs: TaskObs) -> None:
    shapes = dict(
        q=(3,),
        qd=(3,),
        M=(3, 3),
        h=(3,),
        x_e=(2,),
        xd_e=(2,),
        J=(2, 3),
        jdot_qdot=(2,),
        f_int=(2,),
        x_o=(2,),
        xd_o=(2,),
    )
    for k, s in shapes.items():
        got = tuple(jnp.shape(getattr(obs, k)))
        if got != s:
            raise ValueError(f"TaskObs.{k} must have shape {s}, got {got}")


def difference_over_elapsed(one_step, dt, dt_elapsed):
    """A one-step backward difference ``one_step`` (over ``dt``) as the mean over ``dt_elapsed``
    [s] (None: unchanged). Selected, not rescaled, at ``dt_elapsed == dt``: XLA may compile a
    division by the constant ``dt`` differently from one by a traced value.
    """
    if dt_elapsed is None:
        return one_step
    return jnp.where(dt_elapsed == dt, one_step, one_step * (dt / dt_elapsed))


def make_impedance_controller(
    dt: float, torque_limit, cfg: ControllerConfig | None = None
) -> tuple[Init, Apply]:
    """Factory of the non-contact impedance controller (Eqs. 41-48) as pure (init, apply).

    Args:
        dt: [s] control period (backward differences for X_e'', X_o''); the plant's time step.
        torque_limit: [N m] (3,) symmetric saturation (the actuators' ctrlrange).
        cfg: controller settings (default ``ControllerConfig()``).

    ``apply(params, vparams, target, state, obs, dt_elapsed=None) -> (tau, state, info)``;
    shapes are checked at trace time (ValueError); values are not (use
    ``impedance_params``/``virtual_params``). Setting ``vparams`` to zeros gives plain impedance
    control (F_o = 0). ``dt_elapsed`` [s]: the time since the previous call, where it is not
    ``dt`` (a wall-clock loop that skipped steps: the backward differences span the gap); None:
    ``dt``, and the traced program is the one without the argument.
    """
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt}")
    limit = np.asarray(torque_limit, dtype=float)
    if limit.shape != (3,) or not np.all(limit > 0):
        raise ValueError(f"torque_limit must be 3 positive values, got {torque_limit}")
    cfg = DEFAULT_CONFIG if cfg is None else cfg
    limit = jnp.asarray(limit)

    def init(obs: TaskObs) -> ControllerState:
        _check_obs_shapes(obs)
        return ControllerState(q_posture=obs.q, xd_e_prev=obs.xd_e, xd_o_prev=obs.xd_o)

    def apply(params, vparams, target, state, obs, dt_elapsed=None):
        _check_obs_shapes(obs)
        # [m/s^2], one sample old; over a longer time since the previous call, its mean (the
        # one-step difference itself, bit for bit, where dt_elapsed is dt)
        xdd_e = difference_over_elapsed((obs.xd_e - state.xd_e_prev) / dt, dt, dt_elapsed)
        if obs.xdd_o is None:
            xdd_o = difference_over_elapsed((obs.xd_o - state.xd_o_prev) / dt, dt, dt_elapsed)
        else:  # from an estimator (a piecewise prediction would spike under differencing)
            xdd_o = obs.xdd_o
        sk = sphere_kinematics(obs.x_o - obs.x_e, obs.xd_o - obs.xd_e, xdd_o - xdd_e, vparams.r)
        f_o = virtual_force(vparams, sk)  # Eq. 47
        # a non-finite object estimate (NaN/inf) gives no virtual force, never a NaN torque
        f_o = jnp.where(jnp.isfinite(f_o), f_o, 0.0)
        tau_cmd, cond = impedance_torque(obs, params, target, f_o, state.q_posture, cfg)
        tau = jnp.clip(tau_cmd, -limit, limit)
        info = ControlInfo(
            tau_cmd=tau_cmd,
            f_o=f_o,
            mx_cond=cond,
            # NaN counts as saturated (mx_damping = 0 at a singular J: M_x = 0/0)
            saturated=~jnp.all(jnp.abs(tau_cmd) <= limit),
            sphere=sk,
            xdd_e=xdd_e,
        )
        new_state = state._replace(xd_e_prev=obs.xd_e, xd_o_prev=obs.xd_o)
        return tau, new_state, info

    return init, apply
