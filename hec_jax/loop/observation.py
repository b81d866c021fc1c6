"""Simulator data -> the task-space observation the hand reads (``hec_jax.control.TaskObs``).

Task space: the vertical plane, X = (x, z) [m] in the world frame (``TASK_AXES``). The arm and the
pendulum are separate kinematic trees, so the joint-space inertia is block diagonal and the 3x3 arm
block is the arm's M(theta) exactly. Two sources with the same result (tested against each other):
MJX data inside a jitted rollout (:func:`observe`) and MuJoCo C quantities (:func:`observe_c`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.control import TaskObs
from hec_jax.mjx_scene import (
    TASK_AXES,
    CQuantities,
    SceneIds,
    SimStep,
    bias_force,
    full_mass_matrix,
    site_jacobians,
    site_position,
)

_AX = np.array(TASK_AXES)


def hand_position(m, d, ids: SceneIds, q_arm: jax.Array) -> jax.Array:
    """X_e(theta) [m] (2,): hand centre in task coordinates at arm angles ``q_arm`` (pure FK)."""
    qpos = d.qpos.at[np.array(ids.arm_qpos)].set(q_arm)
    return site_position(m, d, qpos, ids.hand_site)[_AX]


def task_jacobians(m, d, ids: SceneIds) -> tuple[jax.Array, jax.Array]:
    """(J (2, 3) [m/rad], J' theta' (2,) [m/s^2]) of the hand from MJX's jac / jac_dot.

    Needs the position and velocity stages on ``d``.
    """
    dof = np.array(ids.arm_dof)
    jacp, jacp_dot = site_jacobians(m, d, ids.hand_site, ids.hand_body)
    J = jacp[_AX][:, dof]
    jdot_qdot = jacp_dot[_AX][:, dof] @ d.qvel[dof]
    return J, jdot_qdot


def object_state(m, d, ids: SceneIds) -> tuple[jax.Array, jax.Array]:
    """(X_o [m] (2,), X_o' [m/s] (2,)): cube centre position and velocity in task coordinates."""
    jacp, _ = site_jacobians(m, d, ids.cube_site, ids.cube_body)
    return d.site_xpos[ids.cube_site][_AX], (jacp @ d.qvel)[_AX]


def observe(m, ids: SceneIds, step: SimStep) -> TaskObs:
    """TaskObs from an MJX control step (position/velocity stages done, see ``rollout``)."""
    d = step.d
    dof = np.array(ids.arm_dof)
    M_full = full_mass_matrix(m, d)
    J, jdot_qdot = task_jacobians(m, d, ids)
    x_o, xd_o = object_state(m, d, ids)
    qd = d.qvel[dof]
    return TaskObs(
        q=d.qpos[np.array(ids.arm_qpos)],
        qd=qd,
        M=M_full[dof][:, dof],
        h=bias_force(d)[dof],
        x_e=d.site_xpos[ids.hand_site][_AX],
        xd_e=J @ qd,
        J=J,
        jdot_qdot=jdot_qdot,
        f_int=step.f_int[_AX],
        x_o=x_o,
        xd_o=xd_o,
    )


def observe_c(ids: SceneIds, qpos, qvel, cq: CQuantities, f_int_world) -> TaskObs:
    """TaskObs from MuJoCo C quantities (``hec_jax.mjx_scene.c_quantities``), as float64 arrays."""
    dof = np.array(ids.arm_dof)
    qd = np.asarray(qvel)[dof]
    J = cq.J_hand[_AX][:, dof]
    return TaskObs(
        q=jnp.asarray(np.asarray(qpos)[np.array(ids.arm_qpos)]),
        qd=jnp.asarray(qd),
        M=jnp.asarray(cq.M[dof][:, dof]),
        h=jnp.asarray(cq.h[dof]),
        x_e=jnp.asarray(cq.x_hand[_AX]),
        xd_e=jnp.asarray(J @ qd),
        J=jnp.asarray(J),
        jdot_qdot=jnp.asarray(cq.Jdot_hand[_AX][:, dof] @ qd),
        f_int=jnp.asarray(np.asarray(f_int_world)[_AX]),
        x_o=jnp.asarray(cq.x_cube[_AX]),
        xd_o=jnp.asarray(cq.xd_cube[_AX]),
    )
