"""Simulation of the set-up: state construction, interaction force, closed-loop rollout (MJX and C).

One control step (identical in :func:`rollout` for MJX and :func:`rollout_c` for MuJoCo C):

1. position and velocity stages at the current state (kinematics, M, bias h, passive
   forces, contacts);
2. the policy reads that state and the measured force on the hand and returns the joint torques;
3. actuation, acceleration, constraint solve at those torques; the contact force on the hand from
   this solve is the force measurement the policy sees at the next step (one-sample delay, as a real
   force sensor read before the torque is computed). An applied external force (``f_ext``, on the
   hand body through ``xfrc_applied``) is known exactly and enters the measurement without delay;
4. semi-implicit Euler integration (dt = 1 ms).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hec_jax.mjx_scene import _mjx_internal as internal
from hec_jax.mjx_scene.model import PendulumConditions, SceneIds

# MJX's own code relies on implicit rank promotion; the project runs with
# jax_numpy_rank_promotion="raise" (tests), so every call into MJX is traced under "allow".
_mjx_ctx = functools.partial(jax.numpy_rank_promotion, "allow")


def _allow_promotion(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _mjx_ctx():
            return fn(*args, **kwargs)

    return wrapper


@_allow_promotion
def make_data(
    m: mjx.Model,
    ids: SceneIds,
    c: PendulumConditions,
    q_arm: jax.Array,
    qd_arm: jax.Array | None = None,
) -> mjx.Data:
    """MJX data at t = 0: arm at ``q_arm`` [rad] (3,), pendulum in its release state of ``c``.

    Pure and vmappable over ``c``/``q_arm``. The position/velocity stages are evaluated so that
    ``site_xpos`` etc. are valid.
    """
    if qd_arm is None:
        qd_arm = jnp.zeros(3)
    d = mjx.make_data(m)
    qpos = d.qpos.at[jnp.array(ids.arm_qpos)].set(q_arm).at[ids.pend_qpos].set(c.release_angle)
    qvel = d.qvel.at[jnp.array(ids.arm_dof)].set(qd_arm).at[ids.pend_dof].set(c.release_speed)
    d = d.replace(qpos=qpos, qvel=qvel)
    d = mjx.fwd_position(m, d)
    return mjx.fwd_velocity(m, d)


@_allow_promotion
def hand_contact_force(m: mjx.Model, d: mjx.Data, ids: SceneIds) -> jax.Array:
    """World-frame force [N] (3,) exerted ON the hand geom by contacts (Eq. 39's F_int,
    contact part).

    Valid after the constraint solve. MuJoCo's contact force (contact frame, normal first) is the
    force geom1 exerts on geom2 (checked against mj_contactForce in tests), so the force on the hand
    is +f if the hand is geom2 and -f if it is geom1. Inactive contacts (efc_address < 0) give 0.
    """
    geoms = internal.contact_geoms(d)
    total = jnp.zeros(3)
    for i in range(internal.contact_count(d)):  # static, tiny (one pair: a few contacts at most)
        f = internal.contact_force_world(m, d, i)[:3]
        sign = jnp.where(geoms[i, 1] == ids.hand_geom, 1.0, 0.0) - jnp.where(
            geoms[i, 0] == ids.hand_geom, 1.0, 0.0
        )
        total = total + sign * f
    return total


def hand_contact_force_c(m: mujoco.MjModel, d: mujoco.MjData, ids: SceneIds) -> np.ndarray:
    """MuJoCo C counterpart of :func:`hand_contact_force` via mj_contactForce (world frame, [N])."""
    total = np.zeros(3)
    f6 = np.zeros(6)
    for i in range(d.ncon):
        con = d.contact[i]
        if con.efc_address < 0:
            continue
        mujoco.mj_contactForce(m, d, i, f6)
        f_world = con.frame.reshape(3, 3).T @ f6[:3]
        if con.geom[1] == ids.hand_geom:
            total += f_world
        elif con.geom[0] == ids.hand_geom:
            total -= f_world
    return total


class SimStep(NamedTuple):
    """What a policy sees at one control step.

    Attributes:
        d: MJX data after the position and velocity stages at the current state (qM, qfrc_bias,
            qfrc_passive, site_xpos, cdof, cvel, ... are valid; qacc and contact forces are not).
        f_int: [N] (3,) measured world-frame force ON the hand (contact of the previous solve plus
            the applied external force of this step).
        t: [s] simulation time.
    """

    d: mjx.Data
    f_int: jax.Array
    t: jax.Array


# policy(policy_state, mjx_model, SimStep) -> (ctrl (nu,), new policy_state, aux pytree)
Policy = Callable[[Any, mjx.Model, SimStep], tuple[jax.Array, Any, Any]]


class Trajectory(NamedTuple):
    """Per-step record of a rollout (leading axis: time steps; every row is the state at ``t``).

    Attributes:
        t: [s] (T,) time at the start of the step.
        qpos, qvel: (T, nq), (T, nv) state at ``t`` (before integration).
        ctrl: [N m] (T, nu) torques applied during [t, t + dt].
        f_int: [N] (T, 3) measured force on the hand that the policy used (world frame).
        f_contact: [N] (T, 3) contact force on the hand solved for [t, t + dt] (world frame).
        f_ext: [N] (T, 3) applied external force on the hand during [t, t + dt] (world frame).
        x_hand, x_cube: [m] (T, 3) world positions of the hand centre and cube centre at ``t``.
        sensor_force: [N] (T, 3) reading of the wrist force sensor (site frame) for [t, t + dt].
        aux: whatever the policy returned as aux, stacked over time.
    """

    t: jax.Array
    qpos: jax.Array
    qvel: jax.Array
    ctrl: jax.Array
    f_int: jax.Array
    f_contact: jax.Array
    f_ext: jax.Array
    x_hand: jax.Array
    x_cube: jax.Array
    sensor_force: jax.Array
    aux: Any


def held_at(time, arrival_phase, dt):
    """Whether the pendulum is held at the step starting at ``time`` [s]: the steps k with
    k dt < ``arrival_phase`` (ceil(phase / dt) of them; a phase less than 1e-3 dt above a grid
    point counts as on it), counted on the step grid, so float32 and float64 (and MJX and
    MuJoCo C) hold the same steps. Comparing the accumulated ``time`` with
    the phase, as before 2026-12-04, held one step more in float32 for phases on the 1 ms grid.
    Works on floats (NumPy) and traced arrays (JAX) alike.
    """
    xp = jnp if isinstance(time, jax.Array) or isinstance(arrival_phase, jax.Array) else np
    step = xp.round(time / dt)
    return step < xp.ceil(arrival_phase / dt - 1e-3)


def _hold_pendulum(d: mjx.Data, ids: SceneIds, c: PendulumConditions) -> mjx.Data:
    """Keeps the pendulum in its release state at the steps before arrival_phase (the
    experimenter's hand; :func:`held_at`).
    """
    held = held_at(d.time, c.arrival_phase, ids.timestep)
    qpos = d.qpos.at[ids.pend_qpos].set(jnp.where(held, c.release_angle, d.qpos[ids.pend_qpos]))
    qvel = d.qvel.at[ids.pend_dof].set(jnp.where(held, c.release_speed, d.qvel[ids.pend_dof]))
    return d.replace(qpos=qpos, qvel=qvel)


@_allow_promotion
def observe_stages(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """Step 1 of a control step: position and velocity stages (and their sensors) at the state."""
    d = mjx.fwd_position(m, d)
    d = mjx.sensor_pos(m, d)
    d = mjx.fwd_velocity(m, d)
    return mjx.sensor_vel(m, d)


@_allow_promotion
def dynamics_stages(
    m: mjx.Model, ids: SceneIds, d: mjx.Data, ctrl: jax.Array
) -> tuple[mjx.Data, jax.Array]:
    """Step 3 of a control step: actuation, acceleration and constraint solve at torques ``ctrl``.

    Returns the data before integration (call ``mjx.euler`` to advance) and the world-frame contact
    force on the hand [N] (3,) from this solve. Pure and differentiable in ``ctrl`` (forward mode
    always; reverse mode only with one solver iteration).
    """
    d = mjx.fwd_actuation(m, d.replace(ctrl=ctrl))
    d = mjx.fwd_acceleration(m, d)
    if not internal.has_constraints(d):
        d = d.replace(qacc=d.qacc_smooth)
    else:
        d = mjx.solve(m, d)
    d = mjx.sensor_acc(m, d)
    return d, hand_contact_force(m, d, ids)


def rollout(
    m: mjx.Model,
    ids: SceneIds,
    d0: mjx.Data,
    policy: Policy,
    policy_state0: Any,
    f_ext: jax.Array,
    conditions: PendulumConditions | None = None,
    f_contact0: jax.Array | None = None,
    active: jax.Array | None = None,
    *,
    observe: Callable | None = None,
    dynamics: Callable | None = None,
    checkpoint: bool = False,
) -> tuple[tuple[mjx.Data, Any], Trajectory]:
    """Runs ``policy`` in closed loop for ``f_ext.shape[0]`` steps in one ``lax.scan``
    (pure, jittable).

    Args:
        m: MJX model (after ``apply_conditions`` if conditions are swept).
        ids: static scene ids.
        d0: initial data (e.g. from ``make_data``).
        policy: pure function ``(state, m, SimStep) -> (ctrl, state, aux)``.
        policy_state0: initial policy state (pytree).
        f_ext: [N] (T, 3) world force applied at the hand centre at each step (zeros for none).
        conditions: if given, the pendulum is held in its release state until ``arrival_phase``.
        f_contact0: [N] (3,) contact force on the hand solved at the step before ``d0`` (the first
            force measurement), to continue a rollout in segments; default zeros.
        active: (T,) bool; steps where it is False leave the state (data, policy state, force
            measurement) unchanged and their rows are meaningless: segments of different lengths
            then share one compiled scan. Default: all steps active.
        observe: replacement of :func:`observe_stages` with the same signature.
        dynamics: replacement of :func:`dynamics_stages` with the same signature (e.g.
            ``differentiable.dynamics_stages`` for exact gradients).
        checkpoint: rematerialise each step in the backward pass (``jax.checkpoint`` of the body).

    Returns:
        ((final data, final policy state), Trajectory).
    """
    if f_ext.ndim != 2 or f_ext.shape[1] != 3:
        raise ValueError(f"f_ext must have shape (T, 3), got {f_ext.shape}")
    observe = observe_stages if observe is None else observe
    dynamics = dynamics_stages if dynamics is None else dynamics

    def body(carry, xs):
        f_ext_k, active_k = xs
        d, ps, f_contact_prev = carry
        if conditions is not None:
            d = _hold_pendulum(d, ids, conditions)
        xfrc = jnp.zeros_like(d.xfrc_applied).at[ids.hand_body, :3].set(f_ext_k)
        d = observe(m, d.replace(xfrc_applied=xfrc))
        f_int = f_contact_prev + f_ext_k
        ctrl, ps, aux = policy(ps, m, SimStep(d=d, f_int=f_int, t=d.time))
        d_acc, f_contact = dynamics(m, ids, d, ctrl)
        row = Trajectory(
            t=d_acc.time,
            qpos=d_acc.qpos,
            qvel=d_acc.qvel,
            ctrl=ctrl,
            f_int=f_int,
            f_contact=f_contact,
            f_ext=f_ext_k,
            x_hand=d_acc.site_xpos[ids.hand_site],
            x_cube=d_acc.site_xpos[ids.cube_site],
            sensor_force=d_acc.sensordata[ids.force_sensor_adr : ids.force_sensor_adr + 3],
            aux=aux,
        )
        with _mjx_ctx():
            d = mjx.euler(m, d_acc)
        new = (d, ps, f_contact)
        if active is not None:
            new = jax.tree_util.tree_map(lambda n, o: jnp.where(active_k, n, o), new, carry)
        return new, row

    if checkpoint:
        body = jax.checkpoint(body)
    f0 = jnp.zeros(3, dtype=f_ext.dtype) if f_contact0 is None else f_contact0
    (d, ps, _), traj = jax.lax.scan(body, (d0, policy_state0, f0), (f_ext, active))
    return (d, ps), traj


class CQuantities(NamedTuple):
    """Arm and object quantities computed by MuJoCo C at the current state (NumPy, full nv).

    Attributes:
        M: (nv, nv) joint-space inertia (mj_fullM).
        h: (nv,) qfrc_bias - qfrc_passive (Coriolis, centrifugal, gravity, damping).
        J_hand: (3, nv) translational Jacobian of the hand site (mj_jacSite).
        Jdot_hand: (3, nv) its time derivative (mj_jacDot).
        x_hand, xd_hand: [m], [m/s] (3,) hand centre position and velocity.
        x_cube, xd_cube: [m], [m/s] (3,) cube centre position and velocity.
    """

    M: np.ndarray
    h: np.ndarray
    J_hand: np.ndarray
    Jdot_hand: np.ndarray
    x_hand: np.ndarray
    xd_hand: np.ndarray
    x_cube: np.ndarray
    xd_cube: np.ndarray


def c_quantities(m: mujoco.MjModel, d: mujoco.MjData, ids: SceneIds) -> CQuantities:
    """Reads M, h, Jacobians and site states from MjData (position/velocity stages must be done)."""
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    jh = np.zeros((3, m.nv))
    jdh = np.zeros((3, m.nv))
    jc = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jh, None, ids.hand_site)
    mujoco.mj_jacSite(m, d, jc, None, ids.cube_site)
    mujoco.mj_jacDot(m, d, jdh, None, d.site_xpos[ids.hand_site], ids.hand_body)
    return CQuantities(
        M=M,
        h=d.qfrc_bias - d.qfrc_passive,
        J_hand=jh,
        Jdot_hand=jdh,
        x_hand=d.site_xpos[ids.hand_site].copy(),
        xd_hand=jh @ d.qvel,
        x_cube=d.site_xpos[ids.cube_site].copy(),
        xd_cube=jc @ d.qvel,
    )


def make_data_c(
    m: mujoco.MjModel, ids: SceneIds, c: PendulumConditions, q_arm, qd_arm=None
) -> mujoco.MjData:
    """MuJoCo C counterpart of :func:`make_data` (scalar conditions)."""
    d = mujoco.MjData(m)
    d.qpos[list(ids.arm_qpos)] = np.asarray(q_arm)
    d.qpos[ids.pend_qpos] = float(c.release_angle)
    if qd_arm is not None:
        d.qvel[list(ids.arm_dof)] = np.asarray(qd_arm)
    d.qvel[ids.pend_dof] = float(c.release_speed)
    mujoco.mj_forward(m, d)
    return d


# c_policy(state, MjModel, MjData, CQuantities, f_int (3,), t) -> (ctrl, state, aux)
CPolicy = Callable[..., tuple[np.ndarray, Any, Any]]


def rollout_c(
    m: mujoco.MjModel,
    ids: SceneIds,
    d: mujoco.MjData,
    policy: CPolicy,
    policy_state0: Any,
    f_ext: np.ndarray,
    conditions: PendulumConditions | None = None,
) -> tuple[Any, dict[str, np.ndarray]]:
    """The step sequence of :func:`rollout` with MuJoCo C (Python loop; ``d`` is advanced in place).

    Returns the final policy state and a dict of stacked per-step arrays with the Trajectory names.
    """
    rows: dict[str, list] = {
        k: []
        for k in ("t", "qpos", "qvel", "ctrl", "f_int", "f_contact", "f_ext", "x_hand", "x_cube")
    }
    rows["sensor_force"] = []
    rows["aux"] = []
    f_contact = np.zeros(3)
    ps = policy_state0
    adr = ids.force_sensor_adr
    for k in range(f_ext.shape[0]):
        if conditions is not None and held_at(
            d.time, float(conditions.arrival_phase), m.opt.timestep
        ):
            d.qpos[ids.pend_qpos] = float(conditions.release_angle)
            d.qvel[ids.pend_dof] = float(conditions.release_speed)
        d.xfrc_applied[:] = 0.0
        d.xfrc_applied[ids.hand_body, :3] = f_ext[k]
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_sensorPos(m, d)
        mujoco.mj_fwdVelocity(m, d)
        mujoco.mj_sensorVel(m, d)
        q = c_quantities(m, d, ids)
        f_int = f_contact + f_ext[k]
        ctrl, ps, aux = policy(ps, m, d, q, f_int, d.time)
        d.ctrl[:] = np.asarray(ctrl)
        mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, 1)
        mujoco.mj_sensorAcc(m, d)
        f_contact = hand_contact_force_c(m, d, ids)
        for key, val in (
            ("t", d.time),
            ("qpos", d.qpos.copy()),
            ("qvel", d.qvel.copy()),
            ("ctrl", np.asarray(ctrl).copy()),
            ("f_int", f_int.copy()),
            ("f_contact", f_contact.copy()),
            ("f_ext", np.asarray(f_ext[k]).copy()),
            ("x_hand", q.x_hand),
            ("x_cube", q.x_cube),
            ("sensor_force", d.sensordata[adr : adr + 3].copy()),
        ):
            rows[key].append(val)
        rows["aux"].append(aux)
        mujoco.mj_Euler(m, d)
    out = {k: np.asarray(v) for k, v in rows.items() if k != "aux"}
    out["aux"] = rows["aux"]
    return ps, out


# --- accessors used by hec_jax.control (so that control needs no direct mujoco import) -----------


@_allow_promotion
def full_mass_matrix(m: mjx.Model, d: mjx.Data) -> jax.Array:
    """Dense joint-space inertia M(theta) (nv, nv) [kg m^2], armature included
    (after fwd_position).
    """
    return mjx.full_m(m, d)


def bias_force(d: mjx.Data) -> jax.Array:
    """h(theta, theta') of Eq. 39 (nv,) [N m]: qfrc_bias (Coriolis, centrifugal, gravity) minus
    qfrc_passive (joint damping), so that M theta'' + h = tau + J^T F (after fwd_velocity).
    """
    return d.qfrc_bias - d.qfrc_passive


@_allow_promotion
def site_jacobians(
    m: mjx.Model, d: mjx.Data, site_id: int, body_id: int
) -> tuple[jax.Array, jax.Array]:
    """Translational Jacobian of a site and its time derivative, both (3, nv) (MuJoCo C layout).

    Uses MJX's ``jac`` (needs fwd_position) and ``jac_dot`` (needs fwd_velocity) at the site
    position.
    """
    point = d.site_xpos[site_id]
    jacp, _ = mjx.jac(m, d, point, body_id)
    jacp_dot, _ = internal.jac_dot(m, d, point, body_id)
    return jacp.T, jacp_dot.T


@_allow_promotion
def site_position(m: mjx.Model, d: mjx.Data, qpos: jax.Array, site_id: int) -> jax.Array:
    """World position [m] (3,) of a site at joint positions ``qpos`` (pure kinematics,
    differentiable).
    """
    return mjx.kinematics(m, d.replace(qpos=qpos)).site_xpos[site_id]
