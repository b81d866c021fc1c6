"""The closed loop's policy: observe -> object state -> learner -> controller, one control step.

:func:`build_loop` wires the world (``hec_jax.mjx_scene``), the hand (``hec_jax.control``) and the
learner (``hec_jax.nets``) for one :class:`~hec_jax.loop.config.TaskConfig`, once: the pendulum's
conditions are not part of it, they come in at call time (``Loop.model_for`` / ``Loop.data_for``,
vmappable), so one compiled function serves every condition. The three conditions of the
experiments (plain, frozen, learned) differ only in two pytree leaves of :class:`Switches`.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.control import (
    ControllerConfig,
    ImpedanceParams,
    Target,
    TaskObs,
    VirtualParams,
    difference_over_elapsed,
    make_impedance_controller,
    sphere_kinematics,
)
from hec_jax.loop.config import TaskConfig
from hec_jax.loop.object_state import (
    TOUCH_DISTANCE,
    EyeInput,
    TouchMemory,
    no_touch,
    touch_object_state,
    truth_eye,
)
from hec_jax.loop.observation import observe, observe_c
from hec_jax.mjx_scene import (
    CUBE_EDGE,
    HAND_RADIUS,
    PendulumConditions,
    SceneIds,
    SimStep,
    apply_conditions,
    load_mj_model,
    load_mjx_model,
    make_data,
    scene_ids,
    set_solver_options,
    solve_posture,
)
from hec_jax.mjx_scene.model import ROD_DENSITY, ROD_RADIUS
from hec_jax.nets import LearnerInputs, SphereGeometry, make_online_learner, stability_margins

CONDITIONS = ("plain", "frozen", "learned")


class Switches(NamedTuple):
    """Pytree leaves selecting the condition (so one compile serves all three) and the source of
    the object's state (simulator or eye).

    Attributes:
        use_virtual: () 0.0: plain impedance (F_o = 0); 1.0: the virtual impedance acts.
        learn: () 0.0: frozen networks; 1.0: online learning.
        eye: the object's state source (:func:`~hec_jax.loop.object_state.truth_eye`: simulator).
        fixed: None: the networks give the virtual impedance; else (2, 3) a constant
            (K_o [N/m], B_o [N s/m], M_o [kg]) per task axis (x, z) used instead of the
            networks' output (the fixed-impedance baseline; a pytree leaf, so a search over
            constant impedances is one ``vmap``).
    """

    use_virtual: jax.Array
    learn: jax.Array
    eye: EyeInput
    fixed: jax.Array | None = None


def switches(condition: str, eye: EyeInput | None = None, fixed=None) -> Switches:
    """The :class:`Switches` of ``condition`` ("plain", "frozen" or "learned"); ``fixed``: a
    constant virtual impedance (2, 3) in place of the networks (``Switches.fixed``).

    Raises:
        ValueError: an unknown condition.
    """
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    return Switches(
        use_virtual=jnp.asarray(0.0 if condition == "plain" else 1.0),
        learn=jnp.asarray(1.0 if condition == "learned" else 0.0),
        eye=truth_eye() if eye is None else eye,
        fixed=None if fixed is None else jnp.asarray(fixed),
    )


class PolicyState(NamedTuple):
    """State the closed loop's policy carries from step to step."""

    controller: Any  # the impedance controller's state
    learner: Any  # LearnerState (weights, latched t_c, ...)
    switches: Switches
    touch: TouchMemory  # used by camera runs only
    # [m/s^2] (2,) the low-passed object acceleration (``TaskConfig.object_accel_tau_s`` > 0 and
    # the simulator's object state); None: no filter (X_o'' a 1 kHz backward difference)
    xdd_o_lowpass: Any = None


class Loop(NamedTuple):
    """The pieces of the closed loop (all pure; ``policy`` plugs into ``mjx_scene.rollout``).

    Attributes:
        config: the task.
        mx: the MJX model without the pendulum's conditions (``model_for`` adds them).
        ids: static scene ids (time step and torque limits included).
        q_home: [rad] (3,) arm posture with the hand at X_d.
        x_home: [m] (2,) X_d.
        swing_steps, final_steps: control steps of a swing and of the continuous run.
        policy: ``(policy_state, m, SimStep) -> (tau, policy_state, aux)``.
        initial_policy_state: ``(m, data, learner_state, switches) -> PolicyState``.
        learner_init: ``(key, dtype) -> LearnerState``.
        policy_obs: ``(policy_state, TaskObs, t[, steps_elapsed]) -> (tau, policy_state, aux)``:
            ``policy`` on an observation however computed (``policy`` is ``observe`` (MJX) then
            this; the real-time loop computes it with MuJoCo C from a plant's joint state,
            :mod:`hec_jax.realtime`); ``t`` [s] the observation's time; ``steps_elapsed``:
            control steps since the previous call (None: one).
        initial_policy_state_obs: ``(TaskObs, learner_state, switches) -> PolicyState``.
    """

    config: TaskConfig
    mx: Any
    ids: SceneIds
    q_home: jax.Array
    x_home: np.ndarray
    swing_steps: int
    final_steps: int
    policy: Any
    initial_policy_state: Any
    learner_init: Any
    policy_obs: Any
    initial_policy_state_obs: Any

    def model_for(self, conditions: PendulumConditions):
        """The MJX model under ``conditions`` (pure, vmappable)."""
        return apply_conditions(self.mx, self.ids, conditions)

    def data_for(self, m, conditions: PendulumConditions):
        """MJX data at the release under ``conditions``, the arm at ``q_home`` (pure)."""
        return make_data(m, self.ids, conditions, self.q_home)


def hold_point(f_cd: float, pendulum: PendulumConditions, k_e: float, m_c=None) -> np.ndarray:
    """X_d (x, z) [m] where a caught cube at rest presses on the hand with ``f_cd`` [N].

    Static balance about the hinge with the contact force along the cube's face normal (lever
    L_c, hinge to cube centre): f_cd L_c = (m_c L_c + m_rod L / 2) g sin(theta); the pendulum is
    held at -theta (on the side the cube comes from), the hand centre is half a cube plus the hand
    radius out along the face normal, and X_d is f_cd / K_e behind it (Eq. 40 at rest:
    K_e (X_e - X_d) = F_int). ``pendulum``: scalar conditions (rod, cube mass, hinge x);
    ``m_c``: the MuJoCo model (for the hinge height and gravity; default scene.xml's).
    """
    m_c = load_mj_model() if m_c is None else m_c
    ids = scene_ids(m_c)
    ceiling = m_c.body_pos[int(m_c.body_parentid[ids.rod_body])]
    hinge = np.array([float(pendulum.hinge_x), ceiling[2]])
    rod, mass = float(pendulum.rod_length), float(pendulum.cube_mass)
    l_c = rod + CUBE_EDGE / 2
    m_rod = ROD_DENSITY * np.pi * ROD_RADIUS**2 * rod
    g = -float(m_c.opt.gravity[2])
    sin_theta = f_cd * l_c / ((mass * l_c + m_rod * rod / 2) * g)
    if not 0 <= sin_theta < 1:
        raise ValueError(f"no hold point: gravity cannot press the cube with {f_cd} N")
    theta = -np.arcsin(sin_theta)
    cube = hinge + l_c * np.array([np.sin(theta), -np.cos(theta)])
    normal = np.array([np.cos(theta), np.sin(theta)])  # cube face toward the hand
    return cube + (CUBE_EDGE / 2 + HAND_RADIUS - f_cd / k_e) * normal


def rest_touch_point(pendulum: PendulumConditions, m_c=None) -> np.ndarray:
    """X_d (x, z) [m] where the hand just touches the hanging cube at the pendulum's rest, on the
    +x side (the cube comes from -x): the cube centre plus half a cube and the hand radius along
    +x. ``pendulum``: scalar conditions (rod, hinge x); ``m_c``: the MuJoCo model (hinge height).
    """
    m_c = load_mj_model() if m_c is None else m_c
    ids = scene_ids(m_c)
    ceiling = m_c.body_pos[int(m_c.body_parentid[ids.rod_body])]
    l_c = float(pendulum.rod_length) + CUBE_EDGE / 2
    return np.array([float(pendulum.hinge_x) + CUBE_EDGE / 2 + HAND_RADIUS, ceiling[2] - l_c])


def with_contact(mx, config: TaskConfig):
    """The MJX model with the task's hand-cube contact parameters (every pair of the scene: there
    is one, ``hand_cube``); unchanged where the config leaves them at None.
    """
    if config.contact_solref is not None:
        ref = jnp.broadcast_to(jnp.asarray(config.contact_solref), mx.pair_solref.shape)
        mx = mx.replace(pair_solref=ref.astype(mx.pair_solref.dtype))
    if config.contact_solimp is not None:
        imp = jnp.broadcast_to(jnp.asarray(config.contact_solimp), mx.pair_solimp.shape)
        mx = mx.replace(pair_solimp=imp.astype(mx.pair_solimp.dtype))
    return mx


def steps(seconds: float, dt: float) -> int:
    """Control steps in ``seconds`` at period ``dt`` (rounded)."""
    return int(round(seconds / dt))


def build_loop(config: TaskConfig) -> Loop:
    """World, hand and learner wired together for ``config`` (no pendulum conditions baked in)."""
    lc = config.learner
    m_c = load_mj_model()
    set_solver_options(
        m_c, config.solver_iterations, config.ls_iterations, config.solver, config.jacobian
    )
    ids = scene_ids(m_c)
    dt = ids.timestep
    mx = with_contact(load_mjx_model(m_c), config)
    imp = config.impedance
    if config.x_home is not None:
        x_home = np.asarray(config.x_home, dtype=float)
    elif config.home == "rest_touch":
        x_home = rest_touch_point(config.pendulum.conditions(), m_c)
    else:
        x_home = hold_point(lc.f_desired, config.pendulum.conditions(), imp.k_e[0], m_c)
    q_home = jnp.asarray(solve_posture(m_c, ids, tuple(float(v) for v in x_home)))
    c_init, c_apply = make_impedance_controller(dt, ids.torque_limit, config.controller)
    l_init, l_update = make_online_learner(lc, dt, imp.m_e, imp.b_e, imp.k_e)
    params = ImpedanceParams(
        m_e=jnp.asarray(imp.m_e), b_e=jnp.asarray(imp.b_e), k_e=jnp.asarray(imp.k_e)
    )
    target = Target(x_d=jnp.asarray(x_home), xd_d=jnp.zeros(2), xdd_d=jnp.zeros(2))

    accel_decay = np.exp(-dt / config.object_accel_tau_s) if config.object_accel_tau_s else 0.0

    def policy(ps: PolicyState, m, step: SimStep):
        return policy_obs(ps, observe(m, ids, step), step.t)

    def policy_obs(ps: PolicyState, obs: TaskObs, t, steps_elapsed=None):
        # steps_elapsed: control steps since the previous call (a wall-clock loop that skipped
        # steps, hec_jax.realtime); the accelerations' backward differences and the low-pass
        # span them (the one-step difference itself, bit for bit, at one step). The
        # learner's sampling interval (Eqs. 54-58) stays one step: dE/dF_act is the effect of
        # the force applied from this sample on the next sample, which the gap just past says
        # nothing about. None: one step, and the traced program is the one without it.
        cs, ls, sw, touch, xdd_o_lowpass = ps
        x_o_true, xd_o_true = obs.x_o, obs.xd_o
        xdd_e = (obs.xd_e - cs.xd_e_prev) / dt  # one sample old, as the controller's
        xdd_o = (obs.xd_o - cs.xd_o_prev) / dt
        dt_elapsed = None if steps_elapsed is None else dt * steps_elapsed
        xdd_e = difference_over_elapsed(xdd_e, dt, dt_elapsed)  # the mean acceleration over the gap
        xdd_o = difference_over_elapsed(xdd_o, dt, dt_elapsed)
        if xdd_o_lowpass is not None:  # first-order low-pass, time constant object_accel_tau_s
            decay = accel_decay
            if steps_elapsed is not None:  # exactly the one-step decay at one step
                decay = jnp.where(steps_elapsed == 1, decay, decay**steps_elapsed)
            xdd_o_lowpass = decay * xdd_o_lowpass + (1.0 - decay) * xdd_o
            xdd_o = xdd_o_lowpass
        in_contact = jnp.sqrt(jnp.sum(obs.f_int**2)) > config.contact_threshold
        # the object as the eye sees it (camera runs) or as simulated (sw.eye.use == 0), with
        # touch over vision (``TouchMemory``): a 30 fps eye with a constant-acceleration filter
        # learns of an impact only some frames after it.
        use_eye = sw.eye.use > 0
        x_eye, xd_eye, xdd_eye, known, touch_new = touch_object_state(
            sw.eye,
            touch,
            t,
            obs.x_e,
            obs.xd_e,
            xdd_e,
            obs.f_int,
            in_contact,
            TOUCH_DISTANCE,
            config.touch_memory_across,
        )
        touch = jax.tree_util.tree_map(
            lambda new, old: jnp.where(use_eye, new, old), touch_new, touch
        )
        obs = obs._replace(
            x_o=jnp.where(use_eye, x_eye, obs.x_o),
            xd_o=jnp.where(use_eye, xd_eye, obs.xd_o),
            xdd_o=jnp.where(use_eye, xdd_eye, xdd_o),
        )
        xdd_o = obs.xdd_o
        # nothing seen or touched (recently): no virtual force and no learning
        seen = jnp.where(use_eye, known, sw.eye.seen > 0)
        sk = sphere_kinematics(obs.x_o - obs.x_e, obs.xd_o - obs.xd_e, xdd_o - xdd_e, lc.radius)
        inputs = LearnerInputs(
            obs.x_e,
            obs.xd_e,
            xdd_e,
            obs.x_o,
            obs.xd_o,
            xdd_o,
            obs.f_int,
            in_contact,
            SphereGeometry(sk.dx_o, sk.dxd_o, sk.dxdd_o),
        )
        keep = (sw.learn > 0) & seen
        ls_new, out = l_update(ls, inputs, keep)
        o = out.impedance if sw.fixed is None else sw.fixed.astype(out.impedance.dtype)
        o = o * (sw.use_virtual * seen)  # (2, 3): K_o, B_o, M_o per axis
        vp = VirtualParams(m_o=o[:, 2], b_o=o[:, 1], k_o=o[:, 0], r=jnp.asarray(lc.radius))
        tau, cs, info = c_apply(params, vp, target, cs, obs, dt_elapsed)
        aux = dict(
            x_e=obs.x_e,
            xd_e=obs.xd_e,
            x_o=obs.x_o,
            xd_o=obs.xd_o,
            x_o_true=x_o_true,
            xd_o_true=xd_o_true,
            object_seen=seen,
            f_int=obs.f_int,
            f_o=info.f_o,
            k_o=o[:, 0],
            b_o=o[:, 1],
            m_o=o[:, 2],
            # Eq. 49 margins of the impedance applied (a fixed one, or zero unseen), not the
            # networks' output where something else was applied
            margins=stability_margins(o, params.m_e, params.b_e, params.k_e),
            energy=out.energy,
            inside=out.inside,
            learning=out.learning,
            inputs_finite=out.finite,
            in_contact=in_contact,
            saturated=info.saturated,
        )
        return tau, PolicyState(cs, ls_new, sw, touch, xdd_o_lowpass), aux

    def initial_policy_state(m, d0, ls, sw):
        obs = observe(m, ids, SimStep(d=d0, f_int=jnp.zeros(3), t=d0.time))
        return initial_policy_state_obs(obs, ls, sw)

    def initial_policy_state_obs(obs: TaskObs, ls, sw):
        dtype = obs.q.dtype
        lowpass = jnp.zeros(2, dtype) if config.object_accel_tau_s else None
        return PolicyState(c_init(obs), ls, sw, no_touch(dtype), lowpass)

    for name in ("swing_s", "settle_s") + (("final_s",) if config.final_s > 0 else ()):
        if steps(getattr(config, name), dt) < 1:
            raise ValueError(
                f"TaskConfig.{name} ({getattr(config, name)} s) is under half a control step "
                f"({dt} s): no step to run or average over"
            )
    return Loop(
        config=config,
        mx=mx,
        ids=ids,
        q_home=q_home,
        x_home=x_home,
        swing_steps=steps(config.swing_s, dt),
        final_steps=steps(config.final_s, dt),
        policy=policy,
        initial_policy_state=initial_policy_state,
        learner_init=l_init,
        policy_obs=policy_obs,
        initial_policy_state_obs=initial_policy_state_obs,
    )


# ---------------------------------------------------------------------------------------------
# Plain impedance control (no learner) for ``rollout`` (MJX) and ``rollout_c`` (MuJoCo C)


def make_mjx_policy(ids: SceneIds, cfg: ControllerConfig | None = None):
    """Returns ``(policy_init(m, d, params, vparams, target), policy)`` for ``rollout``.

    The policy state is ``(params, vparams, target, controller_state)``, so parameters are pytree
    leaves carried through the scan (vmappable, differentiable) and returned unchanged.
    """
    init, apply = make_impedance_controller(ids.timestep, ids.torque_limit, cfg)

    def policy_init(m, d, params: ImpedanceParams, vparams: VirtualParams, target: Target):
        obs = observe(m, ids, SimStep(d=d, f_int=jnp.zeros(3), t=d.time))
        return (params, vparams, target, init(obs))

    def policy(ps, m, step: SimStep):
        params, vparams, target, cs = ps
        obs = observe(m, ids, step)
        tau, cs, info = apply(params, vparams, target, cs, obs)
        aux = dict(
            x_e=obs.x_e,
            xd_e=obs.xd_e,
            x_o=obs.x_o,
            f_o=info.f_o,
            mx_cond=info.mx_cond,
            saturated=info.saturated,
            rho=info.sphere.rho,
        )
        return tau, (params, vparams, target, cs), aux

    return policy_init, policy


def make_c_policy(ids: SceneIds, cfg: ControllerConfig | None = None):
    """The same controller for ``rollout_c`` (jitted ``apply`` on MuJoCo C quantities)."""
    init, apply = make_impedance_controller(ids.timestep, ids.torque_limit, cfg)
    apply_jit = jax.jit(apply)
    init_jit = jax.jit(init)

    def policy_init(d, cq, params, vparams, target):
        obs = observe_c(ids, d.qpos, d.qvel, cq, np.zeros(3))
        return (params, vparams, target, init_jit(obs))

    def policy(ps, m, d, cq, f_int, t):
        params, vparams, target, cs = ps
        obs = observe_c(ids, d.qpos, d.qvel, cq, f_int)
        tau, cs, info = apply_jit(params, vparams, target, cs, obs)
        aux = dict(x_e=np.asarray(obs.x_e), xd_e=np.asarray(obs.xd_e), f_o=np.asarray(info.f_o))
        return np.asarray(tau), (params, vparams, target, cs), aux

    return policy_init, policy
