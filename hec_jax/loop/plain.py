"""Impedance control without the learner: fixed target and virtual impedance, one rollout each.

What ``experiments/impedance_response.py`` (a step force on the hand against the target impedance,
Eq. 40) and ``experiments/avoidance.py`` (the pendulum entering a fixed virtual sphere,
Eqs. 45-48) run: the arm starts at rest at the posture of ``x_home``, X_d is the hand's start
position, and ``hec_jax.loop.policy.make_mjx_policy`` closes the loop in ``mjx_scene.rollout``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import expm

from hec_jax.control import ControllerConfig, ImpedanceParams, Target, VirtualParams
from hec_jax.loop.policy import make_mjx_policy
from hec_jax.mjx_scene import (
    TASK_AXES,
    X_HOME,
    PendulumConditions,
    SceneIds,
    Trajectory,
    apply_conditions,
    load_mj_model,
    load_mjx_model,
    make_data,
    rollout,
    scene_ids,
    solve_posture,
)


class PlainScene(NamedTuple):
    """The scene for plain runs: MJX model (no conditions applied), ids, arm posture at X_home.

    Attributes:
        mx: MJX model as compiled from scene.xml.
        ids: static scene ids (``ids.timestep`` [s] is the control period).
        q_home: [rad] (3,) arm posture with the hand at ``x_home``.
    """

    mx: object
    ids: SceneIds
    q_home: jax.Array


def plain_scene(x_home: tuple[float, float] = X_HOME) -> PlainScene:
    """Loads scene.xml and solves the arm's posture for the hand at ``x_home`` (x, z) [m]."""
    m_c = load_mj_model()
    ids = scene_ids(m_c)
    return PlainScene(load_mjx_model(m_c), ids, jnp.asarray(solve_posture(m_c, ids, x_home)))


def make_plain_run(scene: PlainScene, cfg: ControllerConfig | None = None):
    """``run(params, vparams, conditions, f_ext) -> (Trajectory, x_d)`` (pure; jit/vmap it).

    The arm starts at rest at ``scene.q_home``, the pendulum at its release state under
    ``conditions``; X_d [m] (2,) is the hand's start position; ``f_ext`` [N] (T, 3) is applied on
    the hand body (the controller measures it as F_int without delay). The trajectory's ``aux``
    holds x_e, xd_e, x_o, f_o, mx_cond, saturated and rho (|X_r|) per step.
    """
    pinit, policy = make_mjx_policy(scene.ids, cfg)
    ids = scene.ids

    def run(
        params: ImpedanceParams, vparams: VirtualParams, conditions: PendulumConditions, f_ext
    ) -> tuple[Trajectory, jax.Array]:
        m = apply_conditions(scene.mx, ids, conditions)
        d0 = make_data(m, ids, conditions, scene.q_home)
        x_d = d0.site_xpos[ids.hand_site][np.array(TASK_AXES)]
        ps0 = pinit(m, d0, params, vparams, Target(x_d, jnp.zeros(2), jnp.zeros(2)))
        _, traj = rollout(m, ids, d0, policy, ps0, f_ext, conditions)
        return traj, x_d

    return run


def zoh_reference(m_e: float, b_e: float, k_e: float, f: np.ndarray, dt: float) -> np.ndarray:
    """Exact solution of m_e x'' + b_e x' + k_e x = f (one axis, Eq. 40) from rest, with ``f``
    [N] (T,) held over each step of ``dt`` [s] (the simulator's zero-order hold): (T, 2) rows
    (x [m], x' [m/s]) at the start of each step (matrix exponential; independent of the
    controller).
    """
    A = np.array([[0.0, 1.0], [-k_e / m_e, -b_e / m_e]])
    E = expm(np.block([[A, np.array([[0.0], [1.0 / m_e]])], [np.zeros((1, 3))]]) * dt)
    x = np.zeros(2)
    out = np.empty((len(f), 2))
    for i, fk in enumerate(f):
        out[i] = x
        x = E[:2, :2] @ x + E[:2, 2] * fk
    return out


def contact_summary(traj: Trajectory, t: np.ndarray) -> dict:
    """First contact [s], peak contact force [N], largest hand retreat along +x [m] and smallest
    hand-object distance |X_r| [m] of one plain run (NumPy trajectory, no batch axis).
    """
    fc = np.linalg.norm(traj.f_contact, axis=1)
    hit = np.nonzero(fc > 0)[0]
    x_e = traj.aux["x_e"]
    return dict(
        first_contact_s=float(t[hit[0]]) if hit.size else None,
        peak_contact_force_N=float(fc.max()),
        max_hand_retreat_x_m=float((x_e[:, 0] - x_e[0, 0]).max()),
        min_distance_m=float(traj.aux["rho"].min()),
    )
