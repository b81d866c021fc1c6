"""The online learner of Eqs. 52-53 with the exact one-step dE/dF_act in place of Eqs. 55-58.

``build_exact_loop(config, pendulum)`` returns ``task_loop.build_loop``'s :class:`Loop` with its
policy replaced: per sample the learner's own ``update`` (``hec_jax.nets``, unchanged) does the
bookkeeping (sphere entry, latched X_r'(t_c), contact flag, outputs, the paper's step), then the
weight step is redone with

    dE/dF_act = dE/dX_e . dX_e(t + dt)/dF_act + dE/dX_e' . dX_e'(t + dt)/dF_act,

the Jacobian taken by forward mode (``jax.jacfwd``, 2 columns) through one full control step of the
world at the current state: impedance law (Eqs. 41-44) with F_act = F_o, torque saturation, MJX
actuation and contact solve (``hec_jax.mjx_scene.differentiable``), semi-implicit Euler and the next
observation. The paper's unit-mass Jacobian is dt^2 I and dt I. The weight step is the learner's:
w <- w - eta (dE/dF_act)^T dF_o/dw, by one VJP through Eq. 47 and the networks (Eqs. 50-51),
composed here from ``hec_jax.nets``' public functions (the learner exposes no hook for the
gradient; see the report of issue 6).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from experiments import task_loop as tl
from hec_jax.control import (
    ImpedanceParams,
    Target,
    VirtualParams,
    impedance_torque,
    make_impedance_controller,
    observe,
    task_jacobians,
)
from hec_jax.mjx_scene import TASK_AXES, SimStep, differentiable, observe_stages
from hec_jax.nets import LearnerInputs, make_online_learner, task_energy
from hec_jax.nets import impedance_nets as nets
from hec_jax.nets.learner import _norm


def build_exact_loop(config: tl.TaskConfig, pendulum) -> tl.Loop:
    base = tl.build_loop(config, pendulum)
    lc, cc = config.learner, config.controller
    ids = base.ids
    _, c_apply = make_impedance_controller(cc)
    _, l_update = make_online_learner(lc, tl.sphere_fn)
    params = ImpedanceParams(
        m_e=jnp.asarray(lc.m_e), b_e=jnp.asarray(lc.b_e), k_e=jnp.asarray(lc.k_e)
    )
    target = Target(x_d=jnp.asarray(config.x_home), xd_d=jnp.zeros(2), xdd_d=jnp.zeros(2))
    u = nets.u_max(lc.net, jnp.asarray(lc.m_e), jnp.asarray(lc.b_e), jnp.asarray(lc.k_e))
    eta = jnp.asarray(lc.eta)
    limit = jnp.asarray(cc.torque_limit)
    axes = np.array(TASK_AXES)
    dof = np.array(ids.arm_dof)
    dt = cc.dt

    def one_step(m, d, obs, cs, f_o):
        """F_act -> (X_e, X_e')(t + dt) (4,): one control step of the world."""
        tau_cmd, _ = impedance_torque(obs, params, target, f_o, cs.q_posture, cc)
        d_acc, _ = differentiable.dynamics_stages(m, ids, d, jnp.clip(tau_cmd, -limit, limit))
        with jax.numpy_rank_promotion("allow"):
            d1 = observe_stages(m, mjx.euler(m, d_acc))
        J, _ = task_jacobians(m, d1, ids)
        return jnp.concatenate([d1.site_xpos[ids.hand_site][axes], J @ d1.qvel[dof]])

    def policy(ps, m, step: SimStep):
        cs, ls, sw, touch = ps
        obs = observe(m, ids, step)
        xdd_e = (obs.xd_e - cs.xd_e_prev) / dt
        xdd_o = (obs.xd_o - cs.xd_o_prev) / dt
        in_contact = jnp.sqrt(jnp.sum(obs.f_int**2)) > config.contact_threshold
        inputs = LearnerInputs(
            obs.x_e, obs.xd_e, xdd_e, obs.x_o, obs.xd_o, xdd_o, obs.f_int, in_contact
        )
        ls_new, out = l_update(ls, inputs)  # bookkeeping (its paper step is replaced below)
        o = out.impedance * sw.use_virtual
        vp = VirtualParams(m_o=o[:, 2], b_o=o[:, 1], k_o=o[:, 0], r=jnp.asarray(lc.radius))
        tau, cs_new, info = c_apply(params, vp, target, cs, obs)

        # exact one-step dE/dF_act
        jac = jax.jacfwd(lambda f: one_step(m, step.d, obs, cs, f))(info.f_o)  # (4, 2)
        de_dx, de_dxd = jax.grad(
            lambda a, b: task_energy(lc, a, b, inputs, ls_new.xd_r_tc, ls_new.touched),
            argnums=(0, 1),
        )(inputs.x_e, inputs.xd_e)
        de_df = jnp.concatenate([de_dx, de_dxd]) @ jac
        cot = jnp.where(out.learning, de_df, 0.0)

        # weight step through Eq. 47 and the networks, as the learner's
        x_r, xd_r = inputs.x_o - inputs.x_e, inputs.xd_o - inputs.xd_e
        inside = _norm(x_r) <= lc.radius
        geo = tl.sphere_fn(x_r, xd_r, xdd_o - xdd_e, lc.radius)
        net_in = nets.normalise_inputs(lc.net, x_r, xd_r, xdd_o - xdd_e, inputs.f_int)
        terms = jnp.stack([geo.dx_o, geo.dxd_o, geo.dxdd_o], axis=-1)

        def f_o_of(p):
            oo = nets.apply(p, lc.net, net_in, u.astype(net_in.dtype))
            return jnp.where(inside, jnp.sum(oo * terms.astype(oo.dtype), axis=-1), 0.0)

        f_o_val, pull = jax.vjp(f_o_of, ls.params)
        (g,) = pull(cot.astype(f_o_val.dtype))
        lr = lambda x: eta.reshape((1, 3) + (1,) * (x.ndim - 2)).astype(x.dtype)  # noqa: E731
        keep = sw.learn > 0
        new_params = jax.tree_util.tree_map(
            lambda w, gw: jnp.where(keep, w - lr(gw) * gw, w), ls.params, g
        )
        ls_new = ls_new._replace(params=new_params)
        aux = dict(
            x_e=obs.x_e,
            xd_e=obs.xd_e,
            x_o=obs.x_o,
            xd_o=obs.xd_o,
            f_int=obs.f_int,
            f_o=info.f_o,
            margins=out.margins,
            energy=out.energy,
            inside=out.inside,
            learning=out.learning & keep,
            in_contact=in_contact,
            de_df_exact=cot,
            de_df_paper=jnp.where(out.learning, out.de_df_act, 0.0),
        )
        return tau, tl.PolicyState(cs_new, ls_new, sw, touch), aux

    return base._replace(policy=policy)


def make_exact_sweep(config: tl.TaskConfig):
    """``task_loop.make_sweep`` with the exact one-step learner (not jitted)."""
    from hec_jax.mjx_scene import default_conditions

    run_one_seed = tl._make_seed_run(config, build_exact_loop(config, default_conditions()))
    return jax.vmap(run_one_seed, in_axes=(0, None, 0))
