"""A small closed loop with contact for gradient checks: the hand held by a PD law, the pendulum
swinging into it (no learner, so that it compiles in seconds).

``make_probe(iterations=None)`` returns a :class:`Probe` whose ``loss(gains, conditions, steps,
rollout_fn)`` runs ``steps`` 1 ms control steps from the release and returns a scalar loss of the
contact force and the hand path. ``gains`` (3,) = (log K_p scale, log K_d scale, torque offset) is
the differentiated parameter vector. Pure, jittable, vmappable over ``conditions``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.mjx_scene import differentiable
from hec_jax.mjx_scene.model import (
    X_HOME,
    PendulumConditions,
    SceneIds,
    apply_conditions,
    default_conditions,
    load_mj_model,
    load_mjx_model,
    scene_ids,
    solve_posture,
)
from hec_jax.mjx_scene.sim import SimStep, make_data, rollout

KP = np.array([400.0, 200.0, 40.0])  # [N m/rad] nominal PD gains of the three arm joints
KD = np.array([20.0, 10.0, 2.0])  # [N m s/rad]


class Probe(NamedTuple):
    """The contact probe: model, ids, the hand's home posture and its loss function."""

    mx: object
    ids: SceneIds
    q_home: jax.Array
    loss: object  # (gains (3,), conditions, steps: static, rollout_fn: static) -> (loss, f_contact)
    start: object  # (conditions) -> MJX data at the release


def make_probe(iterations: int | None = None, hold_steps: int = 0) -> Probe:
    """The probe loop. ``iterations``: MJX solver iterations (None: the scene's own)."""
    m_c = load_mj_model()
    if iterations is not None:
        m_c.opt.iterations = iterations
        m_c.opt.ls_iterations = max(iterations, 1)
    ids = scene_ids(m_c)
    mx0 = load_mjx_model(m_c)
    q_home = jnp.asarray(solve_posture(m_c, ids, X_HOME))
    dof = np.array(ids.arm_dof)
    qadr = np.array(ids.arm_qpos)

    def policy(gains, m, step: SimStep):
        d = step.d
        dtype = d.qpos.dtype
        kp = jnp.asarray(KP, dtype) * jnp.exp(gains[0])
        kd = jnp.asarray(KD, dtype) * jnp.exp(gains[1])
        tau = (
            d.qfrc_bias[dof]
            + kp * (q_home.astype(dtype) - d.qpos[qadr])
            - kd * d.qvel[dof]
            + gains[2]
        )
        return tau, gains, jnp.zeros(())

    def start(conditions: PendulumConditions):
        m = apply_conditions(mx0, ids, conditions)
        return m, make_data(m, ids, conditions, q_home)

    def loss(gains, conditions, steps, rollout_fn=rollout):
        m, d0 = start(conditions)
        f_ext = jnp.zeros((steps, 3), gains.dtype)
        _, traj = rollout_fn(m, ids, d0, policy, gains, f_ext, None)
        f2 = jnp.sum(traj.f_contact**2, axis=-1)
        value = 1e-3 * jnp.sum(f2) + 10.0 * jnp.sum(traj.x_hand[:, 0] - X_HOME[0])
        return value, traj.f_contact

    return Probe(mx0, ids, q_home, loss, start)


def probe_conditions(n: int, seed: int = 0, dtype=jnp.float64) -> PendulumConditions:
    """``n`` pendulum conditions around the default whose swings hit the hand within ~0.5 s."""
    rng = np.random.default_rng(seed)
    base = default_conditions()
    fields = {
        "rod_length": rng.uniform(0.55, 0.65, n),
        "cube_mass": rng.uniform(0.5, 0.9, n),
        "release_angle": rng.uniform(-0.6, -0.45, n),
        "release_speed": np.zeros(n),
        "hinge_damping": np.full(n, float(base.hinge_damping)),
        "arrival_phase": np.zeros(n),
        "hinge_x": np.full(n, float(base.hinge_x)),
    }
    return PendulumConditions(**{k: jnp.asarray(v, dtype) for k, v in fields.items()})


ROLLOUTS = {"unrolled": rollout, "implicit": differentiable.rollout}
