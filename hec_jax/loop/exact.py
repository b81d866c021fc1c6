"""The exact one-step sensitivity d(X_e, X_e')(t + dt) / dF_act(t) through one MJX control step,
and the online learner of Eqs. 52-53 that uses it in place of Eqs. 55-58.

Eqs. 55-58 treat the hand as a unit mass over one sample: dX_e/dF_act = dt^2 I and
dX_e'/dF_act = dt I (docs/paper_readings.md, Eqs. 52-58). Here the Jacobian is taken by forward
mode (``jax.jacfwd``, 2 columns) through one full control step of the world: impedance law
(Eqs. 41-44) with F_act = F_o entering as in Eq. 48, torque saturation, MJX actuation and
constraint solve (contact), semi-implicit Euler and the next observation. Measured against the
unit-mass rule in docs/gradients.md.

:func:`build_exact_loop` returns :func:`hec_jax.loop.build_loop`'s :class:`Loop` with its policy
replaced: per sample the learner's own ``update`` (``hec_jax.nets``, unchanged) does the
bookkeeping (sphere entry, latched X_r'(t_c), contact flag, outputs, the paper's step), then the
weight step is redone with

    dE/dF_act = dE/dX_e . dX_e(t + dt)/dF_act + dE/dX_e' . dX_e'(t + dt)/dF_act,

as w <- w - eta (dE/dF_act)^T dF_o/dw, by one VJP through Eq. 47 and the networks (Eqs. 50-51),
composed from ``hec_jax.nets``' public functions (the learner exposes no hook for the gradient).
The object state is the simulator's (no eye).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from hec_jax.control import (
    ImpedanceParams,
    Target,
    VirtualParams,
    impedance_torque,
    make_impedance_controller,
    sphere_kinematics,
)
from hec_jax.loop.config import TaskConfig
from hec_jax.loop.observation import observe, task_jacobians
from hec_jax.loop.policy import Loop, PolicyState, build_loop
from hec_jax.mjx_scene import TASK_AXES, SimStep, differentiable, dynamics_stages, observe_stages
from hec_jax.nets import LearnerInputs, SphereGeometry, make_online_learner, task_energy
from hec_jax.nets import impedance_nets as nets

_AX = np.array(TASK_AXES)


def _impedance(config: TaskConfig) -> ImpedanceParams:
    imp = config.impedance
    return ImpedanceParams(jnp.asarray(imp.m_e), jnp.asarray(imp.b_e), jnp.asarray(imp.k_e))


def make_control_step(loop: Loop, dynamics=dynamics_stages):
    """``step(m, d, obs, q_posture, f_o) -> (X_e, X_e')(t + dt)`` [m, m/s] (4,): one control step
    of the world from observed data ``d`` (position/velocity stages done) under the virtual force
    ``f_o`` [N] (2,), the loop's target impedance and X_d. ``dynamics``: ``mjx_scene``'s stages
    (forward mode through MJX's solve) or ``differentiable.dynamics_stages`` (implicit).
    """
    cc, ids = loop.config.controller, loop.ids
    params = _impedance(loop.config)
    target = Target(jnp.asarray(loop.x_home), jnp.zeros(2), jnp.zeros(2))
    limit = jnp.asarray(ids.torque_limit)
    dof = np.array(ids.arm_dof)

    def step(m, d, obs, q_posture, f_o):
        tau, _ = impedance_torque(obs, params, target, f_o, q_posture, cc)
        d_acc, _ = dynamics(m, ids, d, jnp.clip(tau, -limit, limit))
        with jax.numpy_rank_promotion("allow"):
            d1 = observe_stages(m, mjx.euler(m, d_acc))
        J, _ = task_jacobians(m, d1, ids)
        return jnp.concatenate([d1.site_xpos[ids.hand_site][_AX], J @ d1.qvel[dof]])

    return step


def make_one_step(loop: Loop):
    """``one_step(f_o (2,), qpos, qvel, f_int_world (3,), m) -> (X_e, X_e')(t + dt)`` (4,): one
    control step from a logged state (the posture target is ``loop.q_home``; the measured force
    at step k is the contact force solved at step k - 1). ``m``: the MJX model under the run's
    conditions (``loop.model_for``), an argument so one compile serves every condition.
    """
    c0 = loop.config.pendulum.conditions()
    d_template = loop.data_for(loop.model_for(c0), c0)
    step = make_control_step(loop)

    def one_step(f_o, qpos, qvel, f_int_world, m):
        d = observe_stages(m, d_template.replace(qpos=qpos, qvel=qvel))
        obs = observe(m, loop.ids, SimStep(d=d, f_int=f_int_world, t=d.time))
        return step(m, d, obs, loop.q_home, f_o)

    return one_step


def build_exact_loop(config: TaskConfig) -> Loop:
    """``build_loop(config)`` whose learner steps with the exact one-step dE/dF_act (module
    docstring); its logs add ``de_df_exact`` and ``de_df_paper`` (2,) at learning samples.
    """
    base = build_loop(config)
    lc, ids, imp = config.learner, base.ids, config.impedance
    dt = ids.timestep
    _, c_apply = make_impedance_controller(dt, ids.torque_limit, config.controller)
    _, l_update = make_online_learner(lc, dt, imp.m_e, imp.b_e, imp.k_e)
    params = _impedance(config)
    target = Target(jnp.asarray(base.x_home), jnp.zeros(2), jnp.zeros(2))
    u = nets.u_max(lc.net, params.m_e, params.b_e, params.k_e)
    eta = jnp.asarray(lc.eta)
    step_world = make_control_step(base, differentiable.dynamics_stages)

    accel_decay = np.exp(-dt / config.object_accel_tau_s) if config.object_accel_tau_s else 0.0

    def policy(ps, m, step: SimStep):
        cs, ls, sw, touch, xdd_o_lowpass = ps
        obs = observe(m, ids, step)
        xdd_e = (obs.xd_e - cs.xd_e_prev) / dt
        xdd_o = (obs.xd_o - cs.xd_o_prev) / dt
        if xdd_o_lowpass is not None:  # as build_loop's policy
            xdd_o_lowpass = accel_decay * xdd_o_lowpass + (1.0 - accel_decay) * xdd_o
            xdd_o = xdd_o_lowpass
        obs = obs._replace(xdd_o=xdd_o)
        in_contact = jnp.sqrt(jnp.sum(obs.f_int**2)) > config.contact_threshold
        sk = sphere_kinematics(obs.x_o - obs.x_e, obs.xd_o - obs.xd_e, xdd_o - xdd_e, lc.radius)
        geo = SphereGeometry(sk.dx_o, sk.dxd_o, sk.dxdd_o)
        inputs = LearnerInputs(
            obs.x_e, obs.xd_e, xdd_e, obs.x_o, obs.xd_o, xdd_o, obs.f_int, in_contact, geo
        )
        ls_new, out = l_update(ls, inputs)  # bookkeeping (its paper step is replaced below)
        o = out.impedance * sw.use_virtual
        vp = VirtualParams(m_o=o[:, 2], b_o=o[:, 1], k_o=o[:, 0], r=jnp.asarray(lc.radius))
        tau, cs_new, info = c_apply(params, vp, target, cs, obs)

        # exact one-step dE/dF_act
        jac = jax.jacfwd(lambda f: step_world(m, step.d, obs, cs.q_posture, f))(info.f_o)  # (4, 2)
        de_dx, de_dxd = jax.grad(
            lambda a, b: task_energy(lc, a, b, inputs, ls_new.xd_r_tc, ls_new.touched),
            argnums=(0, 1),
        )(inputs.x_e, inputs.xd_e)
        cot = jnp.where(out.learning, jnp.concatenate([de_dx, de_dxd]) @ jac, 0.0)

        # weight step through Eq. 47 and the networks, as the learner's
        net_in = nets.normalise_inputs(
            lc.net, obs.x_o - obs.x_e, obs.xd_o - obs.xd_e, xdd_o - xdd_e, inputs.f_int
        )
        terms = jnp.stack([geo.dx_o, geo.dxd_o, geo.dxdd_o], axis=-1)

        def f_o_of(p):
            oo = nets.apply(p, lc.net, net_in, u.astype(net_in.dtype))
            return jnp.where(out.inside, jnp.sum(oo * terms.astype(oo.dtype), axis=-1), 0.0)

        f_o_val, pull = jax.vjp(f_o_of, ls.params)
        (g,) = pull(cot.astype(f_o_val.dtype))
        lr = lambda x: eta.reshape((1, 3) + (1,) * (x.ndim - 2)).astype(x.dtype)  # noqa: E731
        keep = sw.learn > 0
        new_params = jax.tree_util.tree_map(
            lambda w, gw: jnp.where(keep, w - lr(gw) * gw, w), ls.params, g
        )
        aux = dict(
            x_e=obs.x_e,
            xd_e=obs.xd_e,
            x_o=obs.x_o,
            xd_o=obs.xd_o,
            x_o_true=obs.x_o,  # the simulator's object state (no eye)
            xd_o_true=obs.xd_o,
            f_int=obs.f_int,
            f_o=info.f_o,
            k_o=o[:, 0],
            b_o=o[:, 1],
            m_o=o[:, 2],
            margins=out.margins,
            energy=out.energy,
            inside=out.inside,
            learning=out.learning & keep,
            in_contact=in_contact,
            de_df_exact=cot,
            de_df_paper=jnp.where(out.learning, out.de_df_act, 0.0),
        )
        ps_new = PolicyState(cs_new, ls_new._replace(params=new_params), sw, touch, xdd_o_lowpass)
        return tau, ps_new, aux

    return base._replace(policy=policy)
