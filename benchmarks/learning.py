"""Learning benchmark: one jitted control + learning step, and closed-loop learning rollouts.

    python benchmarks/learning.py --out runs/bench_learning

Prints a table (and writes ``config.json``, ``metrics.json``, ``table.md``):

* latency of one jitted control + learning step (learner update of Eqs. 52-58 and impedance law of
  Eqs. 41-47 on a given observation: joint state, M, h, J, J'q', F_int, object state), against the
  control-only step (the same impedance law without networks) measured in the same run; target
  <= 100 us (1 kHz with 10x headroom). Also with the observation computed from the MJX state
  (kinematics and dynamics terms), as inside the simulated loop;
* closed-loop rollout throughput (MJX physics + controller + learner, ``vmap`` over a batch) against
  the forward-only baseline (MJX physics + impedance controller, no learner), same batch, same run.
  Every batch member starts from a slightly different release angle, so ``vmap`` cannot hoist the
  computation out of the batch.
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
from hec_jax.control import (  # noqa: E402
    ImpedanceParams,
    VirtualParams,
    fixed_target,
    make_impedance_controller,
    make_mjx_policy,
    observe,
)
from hec_jax.mjx_scene import SimStep, default_conditions, rollout  # noqa: E402
from hec_jax.nets import LearnerConfig, LearnerInputs, make_online_learner  # noqa: E402
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
    p.add_argument("--float32", action="store_true", help="float32 (default float64)")
    args = p.parse_args(argv)
    dtype = jnp.float32 if args.float32 else jnp.float64
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
    ls = loop.learner_init(jax.random.PRNGKey(args.seed), dtype)
    c_init, c_apply = make_impedance_controller(config.controller)
    _, l_update = make_online_learner(lc, tl.sphere_fn)
    obs = jax.jit(observe, static_argnums=1)(loop.mx, loop.ids, step)
    cs = c_init(obs)

    def control_and_learning(cs, ls, obs):
        inputs = LearnerInputs(
            obs.x_e,
            obs.xd_e,
            jnp.zeros(2),
            obs.x_o,
            obs.xd_o,
            jnp.zeros(2),
            obs.f_int,
            jnp.asarray(False),
        )
        ls, out = l_update(ls, inputs)
        o = out.impedance
        vp = VirtualParams(o[:, 2], o[:, 1], o[:, 0], jnp.asarray(lc.radius))
        tau, cs, _ = c_apply(params, vp, target, cs, obs)
        return tau, cs, ls

    def control_only(cs, obs):
        tau, cs, _ = c_apply(params, zero_vp, target, cs, obs)
        return tau, cs

    lat_learn = _time_calls(jax.jit(control_and_learning), (cs, ls, obs), args.repeats)
    lat_plain = _time_calls(jax.jit(control_only), (cs, obs), args.repeats)
    ps_learn = loop.initial_policy_state(d0, ls, tl.switches("learned"))
    ps_plain = plain_init(loop.mx, d0, params, zero_vp, target)
    lat_learn_obs = _time_calls(jax.jit(loop.policy), (ps_learn, loop.mx, step), args.repeats)
    lat_plain_obs = _time_calls(jax.jit(plain_policy), (ps_plain, loop.mx, step), args.repeats)

    # --- rollout throughput ----------------------------------------------------------------------
    f_ext = jnp.zeros((args.steps, 3))
    pend_qpos = loop.ids.pend_qpos

    def start(key):
        d = loop.initial_data()
        angle = d.qpos[pend_qpos] + 1e-3 * jax.random.normal(key, ())  # distinct batch members
        return d.replace(qpos=d.qpos.at[pend_qpos].set(angle))

    def learn_rollout(key):
        d = start(key)
        ps = loop.initial_policy_state(d, loop.learner_init(key, dtype), tl.switches("learned"))
        (_, _), traj = rollout(loop.mx, loop.ids, d, loop.policy, ps, f_ext, None)
        return traj.x_hand

    def plain_rollout(key):
        d = start(key)
        ps = plain_init(loop.mx, d, params, zero_vp, target)
        (_, _), traj = rollout(loop.mx, loop.ids, d, plain_policy, ps, f_ext, None)
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
        f"Device: {jax.devices()[0]} ({jax.default_backend()}), {jnp.dtype(dtype).name}, "
        f"{args.steps}-step rollouts.",
        "",
        "| one jitted step | latency [us] |",
        "|---|---|",
        f"| control + learning on an observation (Eqs. 52-58, 41-47) | {lat_learn * 1e6:.1f} |",
        f"| control only on an observation (Eqs. 41-47) | {lat_plain * 1e6:.1f} |",
        f"| ratio learning / control only | {lat_learn / lat_plain:.2f} |",
        f"| control + learning incl. observation from the MJX state | {lat_learn_obs * 1e6:.1f} |",
        f"| control only incl. observation from the MJX state | {lat_plain_obs * 1e6:.1f} |",
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
        "latency_us": {
            "control_and_learning": lat_learn * 1e6,
            "control_only": lat_plain * 1e6,
            "control_and_learning_with_observe": lat_learn_obs * 1e6,
            "control_only_with_observe": lat_plain_obs * 1e6,
        },
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
