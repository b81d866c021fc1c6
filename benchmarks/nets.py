"""Network step throughput: ``hec_jax.nets.apply`` against the Flax ``nn.Dense`` reference.

    python benchmarks/nets.py [--batch 4096] [--steps 200] [--float64]

The online learner runs, once per sample and per run, the six 4-20-20-1 networks forward, one
vector-Jacobian product back to their weights and the update of Eq. 52 (``hec_jax.nets.learner``).
This times exactly that step inside a ``lax.scan`` over ``--steps`` samples, ``vmap`` over
``--batch`` runs with their own weights, for two forward passes on the same weights:

* ``apply``: weights stored (out, in) (what the learner uses);
* the reference: :class:`hec_jax.nets.FlaxMlp`, ``nn.Dense`` layers with (in, out) kernels
  (matrix products), the weights converted once with :func:`hec_jax.nets.to_flax`.

Inputs, the coefficients of Eq. 47 and the cotangent dE/dF_act vary with the run and the sample,
so nothing can be hoisted out of the batch. Prints steps/s of both and their ratio, and the largest
difference between the two after ``--steps`` updates (same arithmetic, summation order aside).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

if "--float64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from hec_jax import nets  # noqa: E402


def _synthetic_sample(t, run, n_axes, dtype):
    """Per-run, per-sample network inputs (n_axes, 4), Eq. 47 coefficients (n_axes, 3) and
    cotangent (n_axes,), smooth in t and different for every run."""
    s = jnp.sin(0.01 * t + 1e-3 * run + jnp.arange(8 * n_axes, dtype=dtype))
    s = s.reshape(n_axes, 8)
    return s[:, :4], 0.1 * s[:, 4:7], 1e-3 * s[:, 7]


def make_rollout(forward, n_axes, eta, steps, dtype):
    """vmap over runs of a scan over samples of: forward, VJP, w <- w - eta dE/dw (Eq. 52)."""

    def step(params, t, run):
        x, coeff, cotangent = _synthetic_sample(t, run, n_axes, dtype)
        f_o, pullback = jax.vjp(lambda p: jnp.sum(forward(p, x) * coeff, axis=-1), params)
        (grad,) = pullback(cotangent)
        lr = lambda g: eta.reshape((1, 3) + (1,) * (g.ndim - 2))  # noqa: E731
        return jax.tree_util.tree_map(lambda w, g: w - lr(g) * g, params, grad), f_o

    def one_run(params, run):
        samples = jnp.arange(steps, dtype=dtype)
        params, f_o = jax.lax.scan(lambda p, t: step(p, t, run), params, samples)
        return params, f_o[-1]

    return jax.jit(jax.vmap(one_run))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=4096)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--float64", action="store_true")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    dtype = jnp.float64 if args.float64 else jnp.float32
    config = nets.NetConfig()
    n_hidden = len(config.hidden)
    u = nets.u_max(config, jnp.ones(2), 40.0 * jnp.ones(2), 400.0 * jnp.ones(2)).astype(dtype)
    eta = jnp.asarray([0.3, 0.3, 0.3], dtype)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.batch)
    params = jax.vmap(lambda k: nets.init_params(k, config, dtype))(keys)
    flax_params = nets.to_flax(params, n_hidden)
    model = nets.FlaxMlp(config.hidden, config.init_output_std)

    def forward_flax(fp, x):
        per_net = lambda q, v: model.apply({"params": q}, v)  # noqa: E731
        pre = jax.vmap(jax.vmap(per_net, (0, None)), (0, 0))(fp, x)
        return nets.output_unit(pre, u, config.theta)

    def forward_apply(q, x):
        return nets.apply(q, config, x, u)

    runs = jnp.arange(args.batch, dtype=dtype)
    rows = []
    results = {}
    for name, forward, start in (
        ("nets.apply, weights (out, in)", forward_apply, params),
        ("Flax nn.Dense reference, kernels (in, out)", forward_flax, flax_params),
    ):
        fn = make_rollout(forward, config.n_axes, eta, args.steps, dtype)
        t0 = time.perf_counter()
        results[name] = jax.block_until_ready(fn(start, runs))
        compile_s = time.perf_counter() - t0
        best = np.inf
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(start, runs))
            best = min(best, time.perf_counter() - t0)
        rows.append((name, args.batch * args.steps / best, compile_s, best))

    (p_apply, f_apply), (p_flax, f_flax) = results.values()
    weight_diff = max(
        float(jnp.max(jnp.abs(a - b)))
        for a, b in zip(
            jax.tree_util.tree_leaves(nets.to_flax(p_apply, n_hidden)),
            jax.tree_util.tree_leaves(p_flax),
            strict=True,
        )
    )
    device = jax.devices()[0]
    print(
        f"\n{device.device_kind} ({device.platform}), jax {jax.__version__}, "
        f"{jnp.dtype(dtype).name}, batch {args.batch}, {args.steps} samples per run, "
        f"six {'-'.join(map(str, (4, *config.hidden, 1)))} networks per run\n"
    )
    print(f"{'network step (forward + VJP + Eq. 52 update)':50s} {'steps/s':>10s}  notes")
    for name, rate, compile_s, best in rows:
        print(
            f"{name:50s} {rate:10.3g}  compile {compile_s:.0f} s, best of {args.repeats}: {best:.3f} s"
        )
    print(f"\nratio apply / Flax reference = {rows[0][1] / rows[1][1]:.2f}")
    print(
        f"largest difference after {args.steps} updates: weights {weight_diff:.2e}, "
        f"F_o {float(jnp.max(jnp.abs(f_apply - f_flax))):.2e}"
    )


if __name__ == "__main__":
    main()
