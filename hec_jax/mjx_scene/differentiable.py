"""Exact, finite reverse-mode derivatives through MJX's constraint solve (issue 6).

MJX's ``solve`` iterates a Newton (or CG) method with a line search inside a ``while_loop``: reverse
mode cannot run through it at all unless ``opt.iterations == 1``, and with one iteration the
derivative is the derivative of *one truncated Newton step with an early-stopped line search*, not
of the solution of the constraint problem. That derivative is inexact (the line search's stopping
tests are discrete; one iteration is not converged) and, in float32, non-finite: the line search's
Newton update ``alpha - deriv_0 / deriv_1`` is differentiated where ``deriv_1`` (the curvature of
the cost along the search direction) is tiny or exactly ``mjMINVAL`` (search direction ~ 0), whose
derivative ``deriv_0 / deriv_1**2`` overflows float32 (see ``docs/probes.md`` and
``docs/gradients.md``).

Here the solve is differentiated implicitly instead. The constraint problem is

    qacc* = argmin_a  1/2 (a - a_s)^T M (a - a_s) + s(J a - a_ref)        (MuJoCo's primal)

with ``s`` piecewise quadratic (pyramidal or frictionless cones; smooth pieces for the elliptic
cone). Its solution is computed by MJX's own ``solve`` on ``stop_gradient`` inputs (any number of
iterations, forward only), then one Newton step of the same cost is taken from it *with*
derivatives:

    qacc = qacc* - H(qacc*)^{-1} g(qacc*, theta),   H = M + J^T D_active J (+ cone Hessian).

At the solution g = 0, so the value is qacc* (up to the solver's tolerance, and exactly on a
quadratic piece), and the derivative is the implicit-function-theorem derivative
d qacc / d theta = -H^{-1} dg/dtheta of the *converged* solution, with the active set of the
solution held fixed. The cost of the backward pass is one small Cholesky solve per step instead of
unrolling the solver. The Newton step is MJX's own ``Context.create`` (``_update_constraint`` and
``_update_gradient``), so the cone, the friction loss and the constraint scaling are MJX's.

Derivatives are those of the smooth piece that the solution lies on: where a constraint switches
(contact onset, a joint limit engaging) the dynamics are non-smooth and the one-sided derivative is
returned; contact onset is discontinuous in the force (the damping part of the reference
acceleration starts with a jump), so finite differences across it measure a jump, not a slope.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from mujoco import mjx

from hec_jax.mjx_scene import _mjx_internal as internal
from hec_jax.mjx_scene._mjx_internal import SolverType
from hec_jax.mjx_scene.model import SceneIds
from hec_jax.mjx_scene.sim import (
    Policy,
    Trajectory,
    _allow_promotion,
    hand_contact_force,
    observe_stages,
)
from hec_jax.mjx_scene.sim import rollout as sim_rollout


def _stop(tree):
    return jax.tree_util.tree_map(jax.lax.stop_gradient, tree)


def newton_model(m: mjx.Model) -> mjx.Model:
    """``m`` with the Newton solver selected (its Hessian is the one the implicit step needs)."""
    if m.opt.solver == SolverType.NEWTON:
        return m
    return m.replace(opt=m.opt.replace(solver=SolverType.NEWTON))


@_allow_promotion
def solve(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """Constraint solve with implicit derivatives (drop-in for ``mjx.solve`` after
    ``fwd_acceleration``).

    The forward value is MJX's ``solve`` with the model's own solver settings (``while_loop``,
    ``opt.iterations``), run on ``stop_gradient`` copies of ``m`` and ``d``; derivatives (forward
    and reverse mode, any order of ``jit``/``vmap``) come from one Newton step of the constraint
    cost at that solution (module docstring). Sets ``qacc``, ``qfrc_constraint`` and ``efc_force``
    as ``mjx.solve`` does.
    """
    if not internal.has_constraints(d):
        return d.replace(qacc=d.qacc_smooth)
    qacc_star = jax.lax.stop_gradient(mjx.solve(_stop(m), _stop(d)).qacc)
    mn = newton_model(m)
    ctx = internal.solver_context(mn, d.replace(qacc=qacc_star), grad=True)
    qacc = qacc_star - ctx.Mgrad  # Mgrad = H^-1 g (Newton); g ~ 0 at qacc_star
    ctx = internal.solver_context(mn, d.replace(qacc=qacc), grad=False)
    return internal.with_constraint_solution(d, qacc, ctx.qfrc_constraint, ctx.efc_force)


@_allow_promotion
def dynamics_stages(
    m: mjx.Model, ids: SceneIds, d: mjx.Data, ctrl: jax.Array
) -> tuple[mjx.Data, jax.Array]:
    """``hec_jax.mjx_scene.dynamics_stages`` with the implicitly differentiated :func:`solve`.

    Same value (to the solver tolerance); derivatives in ``ctrl`` and the state are exact
    (implicit), finite in float32 and float64, and reverse mode works for any
    ``opt.iterations``.
    """
    d = mjx.fwd_actuation(m, d.replace(ctrl=ctrl))
    d = mjx.fwd_acceleration(m, d)
    d = solve(m, d)
    d = mjx.sensor_acc(m, d)
    return d, hand_contact_force(m, d, ids)


def _floating(x) -> bool:
    return jnp.issubdtype(jnp.asarray(x).dtype, jnp.inexact)


@_allow_promotion
def observe_stages_fwdjac(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """``observe_stages`` whose derivative in (qpos, qvel) is taken by forward mode.

    The state has only nq + nv inputs, so forward mode is an alternative to reverse mode through
    MJX's position stage (kinematics, com, crb, collision, constraint rows). Here the Jacobian of every output leaf with respect to
    (qpos, qvel) is computed by ``jax.jacfwd`` (nq + nv tangents, forward mode) at the current state
    and enters as ``J (x - stop_gradient(x))``: value unchanged (that term is 0), derivative exactly
    J dx in forward and reverse mode. The other inputs (model, applied forces, warm start, ...) keep
    MJX's own derivative.
    """
    nq = d.qpos.shape[0]
    x = jnp.concatenate([d.qpos, d.qvel])
    x0 = jax.lax.stop_gradient(x)
    base = observe_stages(m, d.replace(qpos=x0[:nq], qvel=x0[nq:]))

    def of_state(xs):
        return observe_stages(_stop(m), _stop(d).replace(qpos=xs[:nq], qvel=xs[nq:]))

    jac = jax.lax.stop_gradient(jax.jacfwd(of_state)(x0))
    dx = x - x0

    def add(b, j):
        if not _floating(b) or j.shape[: b.ndim] != b.shape:
            return b
        return b + jnp.tensordot(j, dx, axes=1).astype(b.dtype)

    return jax.tree_util.tree_map(add, base, jac)


def rollout(
    m: mjx.Model,
    ids: SceneIds,
    d0: mjx.Data,
    policy: Policy,
    policy_state0: Any,
    f_ext: jax.Array,
    conditions=None,
    *,
    checkpoint: bool = True,
    observe_jacfwd: bool = False,
) -> tuple[tuple[mjx.Data, Any], Trajectory]:
    """``hec_jax.mjx_scene.rollout`` (same step sequence, same arguments and returns) with the
    differentiable :func:`dynamics_stages`, for reverse mode through closed-loop rollouts (BPTT).

    ``checkpoint``: rematerialise each step in the backward pass (``jax.checkpoint`` of the scan
    body), so the memory of the backward pass does not hold every step's MJX intermediates.
    ``observe_jacfwd``: differentiate the position/velocity stages in the state by forward mode
    (:func:`observe_stages_fwdjac`; same derivative; on CPU not cheaper: 12.4x against 9.7x the
    forward for a 1 s rollout, measured interleaved); False (default): MJX's own reverse mode.
    """
    return sim_rollout(
        m,
        ids,
        d0,
        policy,
        policy_state0,
        f_ext,
        conditions,
        observe=observe_stages_fwdjac if observe_jacfwd else observe_stages,
        dynamics=dynamics_stages,
        checkpoint=checkpoint,
    )


__all__ = ["dynamics_stages", "newton_model", "rollout", "solve"]
