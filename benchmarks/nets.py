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
The networks' bound U (Eq. 51) is taken against the target impedance ``--m-e --b-e --k-e``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from hec_jax import benchmarking as bench
from hec_jax import nets
from hec_jax.cli import command, parse, require
from hec_jax.loop import TargetImpedance


@dataclass(frozen=True)
class NetsBenchmark:
    """The network-step benchmark: the networks, their learning rates, batch and samples."""

    net: nets.NetConfig = field(default_factory=nets.NetConfig)
    impedance: TargetImpedance = field(default_factory=TargetImpedance)
    eta: tuple[float, float, float] = (0.3, 0.3, 0.3)  # learning rates of the VSN, VVN, VIN
    batch: int = 4096  # runs, each with its own weights (vmap)
    steps: int = 200  # samples per run (lax.scan)
    float64: bool = False  # float64 (default float32)
    repeats: int = 3  # timed calls (the best counts)
    seed: int = 0  # PRNG seed of the weights

    def __post_init__(self):
        require(self, "count", "batch", "steps", "repeats")
        require(self, "non_negative", "eta")
        require(self, "seed", "seed")


def _synthetic_sample(t, run, n_axes, dtype):
    """Per-run, per-sample network inputs (n_axes, 4), Eq. 47 coefficients (n_axes, 3) and
    cotangent (n_axes,), smooth in t and different for every run.
    """
    s = jnp.sin(0.01 * t + 1e-3 * run + jnp.arange(8 * n_axes, dtype=dtype))
    s = s.reshape(n_axes, 8)
    return s[:, :4], 0.1 * s[:, 4:7], 1e-3 * s[:, 7]


def make_rollout(forward, n_axes, eta, steps, dtype):
    """Jitted ``vmap`` over runs of a scan over samples: forward, VJP, w -= eta dE/dw (Eq. 52)."""

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


@command
def main(argv=None):
    """Runs the benchmark on the flags in ``argv`` (None: the command line); prints its table."""
    cfg = parse(NetsBenchmark(), argv, __doc__)
    dtype = bench.float_dtype(not cfg.float64)
    config, imp = cfg.net, cfg.impedance
    n_hidden = len(config.hidden)
    u = nets.u_max(config, *(jnp.asarray(v) for v in (imp.m_e, imp.b_e, imp.k_e))).astype(dtype)
    eta = jnp.asarray(cfg.eta, dtype)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed), cfg.batch)
    params = jax.vmap(lambda k: nets.init_params(k, config, dtype))(keys)
    model = nets.FlaxMlp(config.hidden, config.init_output_std)

    def forward_flax(fp, x):
        per_net = lambda q, v: model.apply({"params": q}, v)  # noqa: E731
        pre = jax.vmap(jax.vmap(per_net, (0, None)), (0, 0))(fp, x)
        return nets.output_unit(pre, u, config.theta)

    def forward_apply(q, x):
        return nets.apply(q, config, x, u)

    runs = jnp.arange(cfg.batch, dtype=dtype)
    rows, rates, results = [], [], {}
    for name, forward, start in (
        ("nets.apply, weights (out, in)", forward_apply, params),
        (
            "Flax nn.Dense reference, kernels (in, out)",
            forward_flax,
            nets.to_flax(params, n_hidden),
        ),
    ):
        fn = make_rollout(forward, config.n_axes, eta, cfg.steps, dtype)
        results[name], compile_s = bench.first_call(fn, start, runs)
        best = bench.best_of(lambda fn=fn, s=start: jax.block_until_ready(fn(s, runs)), cfg.repeats)
        note = f"compile {compile_s:.0f} s, best of {cfg.repeats}: {best:.3f} s"
        rates.append(cfg.batch * cfg.steps / best)
        rows.append((name, f"{rates[-1]:.3g}", note))

    (p_apply, f_apply), (p_flax, f_flax) = results.values()
    leaves = zip(
        *(jax.tree_util.tree_leaves(p) for p in (nets.to_flax(p_apply, n_hidden), p_flax)),
        strict=True,
    )
    weight_diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in leaves)
    device = jax.devices()[0]
    print(
        f"\n{device.device_kind} ({device.platform}), jax {jax.__version__}, "
        f"{jnp.dtype(dtype).name}, batch {cfg.batch}, {cfg.steps} samples per run, "
        f"six {'-'.join(map(str, (4, *config.hidden, 1)))} networks per run\n"
    )
    header = ("network step (forward + VJP + Eq. 52 update)", "steps/s", "notes")
    print("\n".join(bench.text_table(header, (50, 10), rows)))
    print(f"\nratio apply / Flax reference = {rates[0] / rates[1]:.2f}")
    print(
        f"largest difference after {cfg.steps} updates: weights {weight_diff:.2e}, "
        f"F_o {float(jnp.max(jnp.abs(f_apply - f_flax))):.2e}"
    )


if __name__ == "__main__":
    main()
