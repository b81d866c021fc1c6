"""Glue between the impedance controller and the set-up (MJX ``rollout``, C ``rollout_c``).

The same ``apply`` function runs on both sides: on MJX quantities inside ``lax.scan`` and, for the
C side, jitted once and called from the Python loop on quantities computed by MuJoCo C
(mj_fullM, qfrc_bias - qfrc_passive, mj_jacSite, mj_jacDot, mj_contactForce).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.control.impedance import (
    DEFAULT_CONFIG,
    ControllerConfig,
    ImpedanceParams,
    Target,
    make_impedance_controller,
)
from hec_jax.control.kinematics import observe, observe_c
from hec_jax.control.virtual import VirtualParams
from hec_jax.mjx_scene import SceneIds, SimStep


def make_mjx_policy(ids: SceneIds, cfg: ControllerConfig = DEFAULT_CONFIG):
    """Returns ``(policy_init(m, d, params, vparams, target), policy)`` for ``rollout``.

    The policy state is ``(params, vparams, target, controller_state)``, so parameters are pytree
    leaves carried through the scan (vmappable, differentiable) and returned unchanged.
    """
    init, apply = make_impedance_controller(cfg)

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


def make_c_policy(ids: SceneIds, cfg: ControllerConfig = DEFAULT_CONFIG):
    """The same controller for ``rollout_c`` (jitted ``apply`` on MuJoCo C quantities)."""
    init, apply = make_impedance_controller(cfg)
    apply_jit = jax.jit(apply)
    init_jit = jax.jit(init)

    def policy_init(d, cq, params, vparams, target):
        obs = observe_c(ids, d.qpos, d.qvel, cq, np.zeros(3))
        return (params, vparams, target, init_jit(obs))

    def policy(ps: Any, m, d, cq, f_int, t):
        params, vparams, target, cs = ps
        obs = observe_c(ids, d.qpos, d.qvel, cq, f_int)
        tau, cs, info = apply_jit(params, vparams, target, cs, obs)
        aux = dict(x_e=np.asarray(obs.x_e), xd_e=np.asarray(obs.xd_e), f_o=np.asarray(info.f_o))
        return np.asarray(tau), (params, vparams, target, cs), aux

    return policy_init, policy
