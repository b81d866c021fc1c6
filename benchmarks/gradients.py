"""Cost of exact gradients through closed-loop MJX rollouts with contact, over the forward rollout.

    python benchmarks/gradients.py [--float32] [--steps 1000] [--batch 1] [--cases probe catching]

One process, one device; every ratio is of times measured in this run (min of ``--repeat`` calls,
compile excluded and reported apart; the repetitions of all rows are interleaved). The forward baseline is ``hec_jax.mjx_scene.rollout`` with the
scene's own solver settings (what the experiments run). Gradients:

* ``implicit``: ``hec_jax.mjx_scene.differentiable.rollout`` (MJX's solve forward, implicit
  derivative of the constraint solve), reverse mode (``value_and_grad``), with and without per-step
  rematerialisation (``jax.checkpoint``), and with the position/velocity stages differentiated by
  their forward-mode Jacobian in the state (``observe_jacfwd``);
* ``unrolled``: reverse mode through MJX's own solve, which needs ``opt.iterations = 1`` (its
  forward is a different, unconverged physics; shown for reference).

Cases: ``probe``: the PD-held hand struck by the pendulum (``contact_probe``), gradient with respect
to 3 gains; ``catching``: the catching loop with the initial (frozen) networks, gradient of
sum |F_contact|^2 + x_hand with respect to all network weights (Eqs. 50-51). Horizon ``--steps``
samples of 1 ms from the release (contact from ~0.55 s). ``--batch`` > 1 vmaps over pendulum
conditions.
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
import numpy as np  # noqa: E402

from hec_jax.mjx_scene import default_conditions, differentiable, rollout  # noqa: E402
from hec_jax.mjx_scene.contact_probe import make_probe, probe_conditions  # noqa: E402
from hec_jax.runs import enable_compile_cache  # noqa: E402


def _timed(fn, *args, repeat):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return min(ts)


def _compiled(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def probe_case(steps, batch, dtype):
    """(forward, {name: value_and_grad}, args) of the PD probe."""
    conds = probe_conditions(batch, 0, dtype)
    gains = jnp.zeros(3, dtype)
    base = make_probe()
    one = make_probe(iterations=1)

    def rf(ck, jacfwd=False):
        return lambda m, ids, d, pol, ps, f, c: differentiable.rollout(
            m, ids, d, pol, ps, f, c, checkpoint=ck, observe_jacfwd=jacfwd
        )

    def batched(fn):
        return jax.jit(jax.vmap(fn, in_axes=(None, 0)))

    forward = batched(lambda g, c: base.loss(g, c, steps, rollout)[0])
    grads = {
        "implicit": batched(jax.value_and_grad(lambda g, c: base.loss(g, c, steps, rf(False))[0])),
        "implicit+remat": batched(
            jax.value_and_grad(lambda g, c: base.loss(g, c, steps, rf(True))[0])
        ),
        "implicit, jacfwd through the stages": batched(
            jax.value_and_grad(lambda g, c: base.loss(g, c, steps, rf(False, True))[0])
        ),
        "implicit, forward mode (jacfwd, 3 tangents)": batched(
            lambda g, c: jax.jacfwd(
                lambda gg: (base.loss(gg, c, steps, rf(False))[0],) * 2, has_aux=True
            )(g)[::-1]
        ),
        "unrolled (iterations=1)": batched(
            jax.value_and_grad(lambda g, c: one.loss(g, c, steps, rollout)[0])
        ),
    }
    return forward, grads, (gains, conds)


def catching_case(steps, batch, dtype):
    from experiments import task_loop as tl
    from hec_jax.nets import LearnerConfig

    config = tl.TaskConfig(learner=LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3))
    loop = tl.build_loop(config, default_conditions())
    ls0 = loop.learner_init(jax.random.PRNGKey(0), dtype)
    conds = probe_conditions(batch, 0, dtype)

    def loss(params, c, fn):
        m = loop.model_for(c)
        d0 = loop.data_for(m, c)
        ps0 = loop.initial_policy_state(d0, ls0._replace(params=params), tl.switches("frozen"))
        _, traj = fn(m, loop.ids, d0, loop.policy, ps0, jnp.zeros((steps, 3), dtype), c)
        return jnp.sum(traj.f_contact**2) * 1e-5 + jnp.sum(traj.x_hand[:, 0])

    def rf(ck):
        return lambda *a: differentiable.rollout(*a, checkpoint=ck)

    def batched(fn):
        return jax.jit(jax.vmap(fn, in_axes=(None, 0)))

    forward = batched(lambda p, c: loss(p, c, rollout))
    grads = {
        "implicit": batched(jax.value_and_grad(lambda p, c: loss(p, c, rf(False)))),
        "implicit+remat": batched(jax.value_and_grad(lambda p, c: loss(p, c, rf(True)))),
    }
    return forward, grads, (ls0.params, conds)


CASES = {"probe": probe_case, "catching": catching_case}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--float32", action="store_true")
    p.add_argument("--steps", type=int, default=1000, help="horizon [samples of 1 ms]")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--skip", nargs="*", default=[], help="gradient variants to skip")
    args = p.parse_args(argv)
    enable_compile_cache()
    dtype = jnp.float32 if args.float32 else jnp.float64
    dev = jax.devices()[0]
    print(
        f"device: {dev.platform} {dev.device_kind}, dtype {jnp.dtype(dtype).name}, horizon "
        f"{args.steps} steps ({args.steps * 1e-3:.1f} s), batch {args.batch}"
    )
    rows = []
    for case in args.cases:
        forward, grads, fargs = CASES[case](args.steps, args.batch, dtype)
        fns = {"forward (rollout)": forward}
        fns.update({f"value_and_grad {k}": v for k, v in grads.items() if k not in args.skip})
        compile_s, finite = {}, {}
        for name, fn in fns.items():
            out, compile_s[name] = _compiled(fn, *fargs)
            leaves = jax.tree_util.tree_leaves(out)
            finite[name] = all(bool(np.all(np.isfinite(x))) for x in leaves)
        times = {name: [] for name in fns}
        for _ in range(args.repeat):  # interleaved, so that load changes hit every row alike
            for name, fn in fns.items():
                times[name].append(_timed(fn, *fargs, repeat=1))
        t_fwd = min(times["forward (rollout)"])
        for name in fns:
            t = min(times[name])
            rows.append((case, name, t, t / t_fwd, compile_s[name], finite[name]))
            print(f"  {case:9s} {name:44s} {t * 1e3:9.1f} ms  x{t / t_fwd:5.2f}", flush=True)
    print()
    print("| case | computation | time [ms] | / forward | compile [s] | finite |")
    print("|---|---|---:|---:|---:|---|")
    for case, name, t, r, c, fin in rows:
        print(f"| {case} | {name} | {t * 1e3:.1f} | {r:.2f} | {c:.1f} | {fin} |")
    return rows


if __name__ == "__main__":
    main()
