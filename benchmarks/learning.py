"""Learning benchmark: one jitted control + learning step, and closed-loop learning rollouts.

    python benchmarks/learning.py --out runs/bench_learning

Prints a table (and writes ``config.json``, ``metrics.json``, ``table.md``):

* latency of one jitted control + learning step (observe, learner update of Eqs. 52-58, impedance
  law of Eqs. 41-47) on a fixed simulation state, against the control-only step (the same impedance
  controller without networks) measured in the same run; target <= 100 us (1 kHz with 10x headroom);
* closed-loop rollout throughput (MJX physics + controller + learner, ``vmap`` over a batch) against
  the forward-only baseline (MJX physics + impedance controller, no learner), same batch, same run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from experiments import task_loop as tl  # noqa: E402
from hec_jax.control import ImpedanceParams, VirtualParams, fixed_target, make_mjx_policy  # noqa: E402
from hec_jax.mjx_scene import SimStep, default_conditions, rollout  # noqa: E402
from hec_jax.nets import LearnerConfig  # noqa: E402
from hec_jax.runs import start_run, write_json, write_text  # noqa: E402


def _time_calls(fn, args, repeats):
    out = fn(*args)
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = fn(*args)
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / repeats


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench_learning"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=500, help="rollout length")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 16, 128])
    p.add_argument("--repeats", type=int, default=2000, help="calls for the latency timing")
    args = p.parse_args(argv)
    folder = start_run(args.out, args.seed, {k: v for k, v in vars(args).items() if k != "seed"})
    config = tl.TaskConfig(learner=LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3))
    pendulum = default_conditions()
    loop = tl.build_loop(config, pendulum)
    lc = config.learner
    params = ImpedanceParams(jnp.asarray(lc.m_e), jnp.asarray(lc.b_e), jnp.asarray(lc.k_e))
    target = fixed_target(config.x_home)
    zero_vp = VirtualParams(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2), jnp.asarray(lc.radius))
    plain_init, plain_policy = make_mjx_policy(loop.ids, config.controller)

    # --- latency of one step -----------------------------------------------------------------
    d0 = loop.initial_data()
    step = SimStep(d=d0, f_int=jnp.zeros(3), t=d0.time)
    ls = loop.learner_init(jax.random.PRNGKey(args.seed), jnp.float64)
    ps_learn = loop.initial_policy_state(d0, ls, tl.switches("learned"))
    ps_plain = plain_init(loop.mx, d0, params, zero_vp, target)
    learn_step = jax.jit(loop.policy)
    plain_step = jax.jit(plain_policy)
    lat_learn = _time_calls(learn_step, (ps_learn, loop.mx, step), args.repeats)
    lat_plain = _time_calls(plain_step, (ps_plain, loop.mx, step), args.repeats)

    # --- rollout throughput ----------------------------------------------------------------------
    f_ext = jnp.zeros((args.steps, 3))

    def learn_rollout(key):
        d = loop.initial_data()
        ps = loop.initial_policy_state(
            d, loop.learner_init(key, jnp.float64), tl.switches("learned")
        )
        (_, _), traj = rollout(loop.mx, loop.ids, d, loop.policy, ps, f_ext, pendulum)
        return traj.x_hand

    def plain_rollout(key):
        d = loop.initial_data()
        ps = plain_init(loop.mx, d, params, zero_vp, target)
        (_, _), traj = rollout(loop.mx, loop.ids, d, plain_policy, ps, f_ext, pendulum)
        return traj.x_hand

    rows = []
    for batch in args.batches:
        keys = jax.random.split(jax.random.PRNGKey(args.seed), batch)
        rates = {}
        for name, fn in (("learning", learn_rollout), ("forward_only", plain_rollout)):
            run = jax.jit(jax.vmap(fn))
            t0 = time.perf_counter()
            jax.block_until_ready(run(keys))
            compile_s = time.perf_counter() - t0
            per_call = _time_calls(run, (keys,), 2)
            rates[name] = (batch * args.steps / per_call, compile_s)
        rows.append((batch, rates))
        print(
            f"batch {batch}: learning {rates['learning'][0]:.3g} steps/s, forward-only "
            f"{rates['forward_only'][0]:.3g} steps/s",
            flush=True,
        )

    lines = [
        f"Device: {jax.devices()[0]} ({jax.default_backend()}), float64, {args.steps}-step rollouts.",
        "",
        "| one jitted step | latency [us] |",
        "|---|---|",
        f"| control + learning (observe, Eqs. 52-58, Eqs. 41-47) | {lat_learn * 1e6:.1f} |",
        f"| control only (same controller, no networks) | {lat_plain * 1e6:.1f} |",
        f"| ratio learning / control only | {lat_learn / lat_plain:.2f} |",
        "",
        "| batch | learning rollout [steps/s] | forward-only rollout [steps/s] | ratio | compile learning [s] |",
        "|---|---|---|---|---|",
    ]
    for batch, r in rows:
        lines.append(
            f"| {batch} | {r['learning'][0]:.3g} | {r['forward_only'][0]:.3g} | "
            f"{r['learning'][0] / r['forward_only'][0]:.2f} | {r['learning'][1]:.1f} |"
        )
    text = "\n".join(lines) + "\n"
    metrics = {
        "latency_us": {"control_and_learning": lat_learn * 1e6, "control_only": lat_plain * 1e6},
        "latency_target_100us_met": bool(lat_learn <= 100e-6),
        "throughput_steps_per_s": {
            str(b): {"learning": r["learning"][0], "forward_only": r["forward_only"][0]}
            for b, r in rows
        },
    }
    write_json(folder / "metrics.json", metrics)
    write_text(folder / "table.md", text)
    print(text)
    return metrics


if __name__ == "__main__":
    main()
