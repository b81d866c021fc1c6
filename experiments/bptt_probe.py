"""Reverse mode through a closed-loop MJX rollout with contact: dL/dw of the network weights (BPTT).

    python experiments/bptt_probe.py --out runs/bptt_probe --seed 0 [--float32]
    python experiments/bptt_probe.py --solver unrolled --iterations 1   # MJX's own solve

Runs the catching loop with the frozen initial networks up to just before contact, then
differentiates L = sum_t (1e-5 |F_contact|^2 + x_hand) over the next ``--steps`` samples (which
include the impact) with respect to all network weights by reverse mode through the rollout
(observation, learner forward pass, impedance law, MJX constraint solve, integration). Reports
whether the gradient is finite and compares its projection on a random direction with central
differences, and the cost of value-and-gradient against the ordinary forward rollout.

``--solver implicit`` (default): ``hec_jax.mjx_scene.differentiable.rollout`` (MJX's converged solve
forward, implicit derivative of the constraint solution; the scene's solver iterations).
``--solver unrolled``: reverse mode through MJX's own solve, which MJX allows only with
``opt.iterations == 1`` (its ``while_loop`` otherwise); the derivative of one truncated Newton step,
non-finite in float32 at near-converged starts (see ``docs/gradients.md``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

if "--float32" not in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from experiments import task_loop as tl  # noqa: E402
from hec_jax.mjx_scene import (  # noqa: E402
    default_conditions,
    differentiable,
    load_mj_model,
    rollout,
)
from hec_jax.nets import LearnerConfig  # noqa: E402
from hec_jax.runs import enable_compile_cache, start_run, write_json  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bptt_probe"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--float32", action="store_true")
    p.add_argument(
        "--solver",
        choices=("implicit", "unrolled"),
        default="implicit",
        help="implicit: hec_jax.mjx_scene.differentiable (any iterations); unrolled: reverse mode "
        "through MJX's own solve (needs --iterations 1)",
    )
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="MJX solver iterations (default: 1 for unrolled, the scene's own for implicit)",
    )
    p.add_argument("--start", type=int, default=540, help="samples run forward first")
    p.add_argument("--steps", type=int, default=60, help="samples differentiated through")
    args = p.parse_args(argv)
    enable_compile_cache()
    folder = start_run(args.out, args.seed, {k: v for k, v in vars(args).items() if k != "seed"})
    dtype = jnp.float32 if args.float32 else jnp.float64
    if args.iterations is None:
        args.iterations = 1 if args.solver == "unrolled" else int(load_mj_model().opt.iterations)
    sim_rollout = rollout if args.solver == "unrolled" else differentiable.rollout

    load_mjx = tl.load_mjx_model

    def with_iterations(m=None):
        m = load_mj_model() if m is None else m
        if args.solver == "unrolled":
            m.opt.iterations = args.iterations
            m.opt.ls_iterations = max(args.iterations, 1)
        return load_mjx(m)

    tl.load_mjx_model = with_iterations  # the scene as it is, with the solver setting changed
    config = tl.TaskConfig(learner=LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3))
    loop = tl.build_loop(config, default_conditions())
    tl.load_mjx_model = load_mjx
    ls0 = loop.learner_init(jax.random.PRNGKey(args.seed), dtype)
    d0 = loop.initial_data()
    ps0 = loop.initial_policy_state(d0, ls0, tl.switches("frozen"))

    def run(d, ps, n, fn=rollout):
        return fn(loop.mx, loop.ids, d, loop.policy, ps, jnp.zeros((n, 3)), None)

    (d_start, ps_start), _ = jax.jit(run, static_argnums=2)(d0, ps0, args.start)

    def loss(params, fn=sim_rollout):
        ps = ps_start._replace(learner=ps_start.learner._replace(params=params))
        (_, _), traj = run(d_start, ps, args.steps, fn)
        return jnp.sum(traj.f_contact**2) * 1e-5 + jnp.sum(traj.x_hand[:, 0]), traj.f_contact

    value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True))
    forward = jax.jit(loss)  # the differentiated function (for the finite differences)
    forward_plain = jax.jit(lambda p: loss(p, rollout))  # the ordinary rollout (cost baseline)
    t0 = time.perf_counter()
    (value, f_contact), grad = jax.block_until_ready(value_and_grad(ls0.params))
    compile_grad = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(forward_plain(ls0.params))
    compile_fwd = time.perf_counter() - t0
    jax.block_until_ready(forward(ls0.params))
    t_grad = min(_timed(value_and_grad, ls0.params) for _ in range(3))
    t_fwd = min(_timed(forward_plain, ls0.params) for _ in range(3))
    value_plain = float(forward_plain(ls0.params)[0])

    leaves = jax.tree_util.tree_leaves(grad)
    finite = all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    direction = jax.tree_util.tree_map(
        lambda w: jax.random.normal(jax.random.PRNGKey(args.seed + 1), w.shape, w.dtype),
        ls0.params,
    )
    h = 1e-6 if dtype == jnp.float64 else 1e-2
    shifted = [
        forward(jax.tree_util.tree_map(lambda w, d, s=s: w + s * h * d, ls0.params, direction))[0]
        for s in (1.0, -1.0)
    ]
    fd = float((shifted[0] - shifted[1]) / (2 * h))
    ad = float(
        sum(
            jnp.sum(g * d)
            for g, d in zip(leaves, jax.tree_util.tree_leaves(direction), strict=True)
        )
    )
    contact_steps = int(jnp.sum(jnp.sum(f_contact**2, axis=-1) > 1e-6))
    metrics = {
        "dtype": jnp.dtype(dtype).name,
        "solver": args.solver,
        "solver_iterations": args.iterations,
        "steps": args.steps,
        "contact_steps": contact_steps,
        "loss": float(value),
        "loss_plain_rollout": value_plain,
        "gradient_finite": finite,
        "directional_autodiff": ad,
        "directional_central_difference": fd,
        "directional_rel_error": abs(ad - fd) / max(abs(fd), 1e-30),
        "cost_value_and_grad_over_forward": t_grad / t_fwd,
        "seconds": {"value_and_grad": t_grad, "forward": t_fwd, "compile_grad": compile_grad,
                    "compile_forward": compile_fwd},
    }  # fmt: skip
    write_json(folder / "metrics.json", metrics)
    print(metrics)
    return metrics


def _timed(fn, x):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(x))
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
