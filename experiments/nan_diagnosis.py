"""Where reverse mode through MJX's constraint solve becomes non-finite (float32, one iteration).

    JAX_ENABLE_X64=0 python experiments/nan_diagnosis.py --out runs/nan_diagnosis --seed 0

Runs the contact probe (``hec_jax.mjx_scene.contact_probe``: PD-held hand, pendulum striking it)
forward with MJX's solver at ``opt.iterations = 1`` for a batch of pendulum conditions, keeps the
MJX data of every step, and evaluates the one-step vector-Jacobian product of the dynamics stage
(actuation, constraint solve; cotangent 1 on every qacc) at every step, with respect to the
torques and every floating input of the data, both through MJX's own (unrolled) solve and through
``hec_jax.mjx_scene.differentiable.solve``. For the first non-finite step it records the line
search's quantities (curvature ``deriv_1`` along the search direction at alpha = 0, |search|,
|grad|) and then re-runs that step's VJP under ``jax_debug_nans`` to name the primitive that first
produces the NaN. Writes ``metrics.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

if os.environ.get("JAX_ENABLE_X64", "0") in ("1", "true", "True"):
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402
from mujoco.mjx._src import solver as mjx_solver  # noqa: E402

from hec_jax.mjx_scene import differentiable  # noqa: E402
from hec_jax.mjx_scene.contact_probe import make_probe, probe_conditions  # noqa: E402
from hec_jax.mjx_scene.sim import (  # noqa: E402
    _allow_promotion,
    dynamics_stages,
    observe_stages,
)
from hec_jax.runs import start_run, write_json  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/nan_diagnosis"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--steps", type=int, default=700)
    args = p.parse_args(argv)
    folder = start_run(args.out, args.seed, {k: v for k, v in vars(args).items() if k != "seed"})
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    probe = make_probe(iterations=1)
    ids = probe.ids
    conds = probe_conditions(args.batch, args.seed, dtype)

    dof = np.array(ids.arm_dof)
    qadr = np.array(ids.arm_qpos)
    from hec_jax.mjx_scene.contact_probe import KD, KP

    @_allow_promotion
    def record(c):
        """Forward rollout keeping the observed data and torques of every step."""
        m, d0 = probe.start(c)

        def body(d, _):
            d = observe_stages(m, d)
            tau = (
                d.qfrc_bias[dof]
                + jnp.asarray(KP, dtype) * (probe.q_home.astype(dtype) - d.qpos[qadr])
                - jnp.asarray(KD, dtype) * d.qvel[dof]
            )
            d_acc, f = dynamics_stages(m, ids, d, tau)
            return mjx.euler(m, d_acc), (d, tau, f)

        _, (ds, taus, fs) = jax.lax.scan(body, d0, None, length=args.steps)
        return m, ds, taus, fs

    def one_step_vjp(m, d, tau, dyn):
        def f(tau, d):
            d_acc, _ = dyn(m, ids, d, tau)
            return d_acc.qacc

        out, pull = jax.vjp(f, tau, d)
        g_tau, g_d = pull(jnp.ones_like(out))
        leaves = [g_tau] + [
            x for x in jax.tree_util.tree_leaves(g_d) if jnp.issubdtype(x.dtype, jnp.floating)
        ]
        return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))

    @_allow_promotion
    def linesearch_stats(m, d, tau):
        d = mjx.fwd_acceleration(m, mjx.fwd_actuation(m, d.replace(ctrl=tau)))
        ctx = mjx_solver.Context.create(m, d.replace(qacc=d.qacc_smooth))
        search_norm = jnp.sqrt(jnp.sum(ctx.search**2))
        jv = d._impl.efc_J @ ctx.search
        quad2 = 0.5 * jnp.sum(d._impl.efc_D * jv * jv * (ctx.Jaref < 0))
        gauss2 = 0.5 * jnp.dot(ctx.search, mjx.full_m(m, d) @ ctx.search)
        # the line search's curvature at alpha = 0 (_LSPoint.create): 2 quad_total[2] (+ mjMINVAL
        # only when exactly 0), and the factor 1 / deriv_1^2 of d(deriv_0 / deriv_1)
        deriv_1 = 2.0 * (quad2 + gauss2)
        deriv_1 = deriv_1 + (deriv_1 == 0) * 1e-15
        return dict(
            search_norm=search_norm,
            grad_norm=jnp.sqrt(jnp.sum(ctx.grad**2)),
            constraint_curvature=quad2,
            ls_deriv_1=deriv_1,
            ls_inverse_deriv_1_squared=1.0 / deriv_1**2,
            n_active=jnp.sum(ctx.Jaref < 0),
        )

    m, ds, taus, fs = jax.jit(jax.vmap(record))(conds)
    in_contact = np.linalg.norm(np.asarray(fs), axis=-1) > 1e-6
    results = {}
    for name, dyn in (("unrolled", dynamics_stages), ("implicit", differentiable.dynamics_stages)):
        fn = jax.jit(
            jax.vmap(
                jax.vmap(lambda m, d, t, f=dyn: one_step_vjp(m, d, t, f), in_axes=(None, 0, 0))
            )
        )
        finite = np.asarray(fn(m, ds, taus))
        results[name] = {
            "steps_nonfinite": int((~finite).sum()),
            "steps_total": int(finite.size),
            "contact_steps": int(in_contact.sum()),
            "contact_steps_nonfinite": int((~finite & in_contact).sum()),
            "free_steps_nonfinite": int((~finite & ~in_contact).sum()),
            "members_with_nonfinite_step": int((~finite).any(1).sum()),
        }
        print(name, results[name])
        if name == "unrolled" and (~finite).any():
            b, k = np.argwhere(~finite)[0]
            pick = lambda x, b=b, k=k: x[b, k]  # noqa: E731
            mb = jax.tree_util.tree_map(lambda x, b=b: x[b], m)
            dk = jax.tree_util.tree_map(pick, ds)
            stats = jax.tree_util.tree_map(float, linesearch_stats(mb, dk, taus[b, k]))
            results["first_nonfinite"] = {
                "member": int(b),
                "step": int(k),
                "in_contact": bool(in_contact[b, k]),
                "contact_steps_before": int(in_contact[b, :k].sum()),
                **stats,
            }
            results["debug_nans"] = _debug_nans(mb, dk, taus[b, k], ids)
            print(results["first_nonfinite"])
            print(results["debug_nans"])
    write_json(folder / "metrics.json", {"dtype": jnp.dtype(dtype).name, **results})
    return results


def _debug_nans(m, d, tau, ids):
    """Re-runs one step's VJP with jax_debug_nans and returns the frames of MJX's code it names."""
    jax.config.update("jax_debug_nans", True)
    try:
        out, pull = jax.vjp(lambda t: dynamics_stages(m, ids, d, t)[0].qacc, tau)
        pull(jnp.ones_like(out))
        return {"raised": False}
    except FloatingPointError as e:
        frames = [
            f"{Path(f.filename).name}:{f.lineno} {f.name}: {f.line}"
            for f in traceback.extract_tb(e.__traceback__)
            if "mjx/_src" in f.filename
        ]
        return {"raised": True, "message": str(e)[:1500], "mjx_frames": frames[-6:]}
    finally:
        jax.config.update("jax_debug_nans", False)


if __name__ == "__main__":
    main()
