"""Cost of exact gradients through closed-loop MJX rollouts with contact, over the forward rollout.

    python benchmarks/gradients.py [--float32] [--steps 1000] [--batch 1] [--cases probe catching]

One process, one device; every ratio is of times measured in this run (min of ``--repeat`` calls,
compile excluded and reported apart; the repetitions of all rows are interleaved). The forward
baseline is ``hec_jax.mjx_scene.rollout`` with the task's solver settings (scene.xml's unless
``--solver...`` are given: what the experiments run). Gradients:

* ``implicit``: ``hec_jax.mjx_scene.differentiable.rollout`` (MJX's solve forward, implicit
  derivative of the constraint solve), reverse mode (``value_and_grad``), with and without per-step
  rematerialisation (``jax.checkpoint``), and with the position/velocity stages differentiated by
  their forward-mode Jacobian in the state (``observe_jacfwd``);
* ``unrolled``: reverse mode through MJX's own solve, which needs ``opt.iterations = 1`` (its
  forward is a different, unconverged physics; shown for reference).

Cases (``hec_jax.benchmarking.GRADIENT_CASES``): ``probe``: the PD-held hand struck by the
pendulum (``contact_probe``), gradient with respect to 3 gains; ``catching``: the catching loop of
the sweep's task (``hec_jax.loop.sweep_catching``; its flags below, swings and durations unused)
with the initial (frozen) networks, gradient of sum |F_contact|^2 + x_hand with respect to all
network weights (Eqs. 50-51). Horizon ``--steps`` samples of 1 ms from the release (contact from
~0.55 s). ``--batch`` > 1 vmaps over pendulum conditions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import jax
import jax.numpy as jnp

from hec_jax import benchmarking as bench
from hec_jax.cli import command, parse, require
from hec_jax.loop import TaskConfig, sweep_catching
from hec_jax.report import markdown_table
from hec_jax.runs import enable_compile_cache


@dataclass(frozen=True)
class GradientsBenchmark:
    """The gradient benchmark: the cases, horizon, batch and repeats."""

    task: TaskConfig = field(default_factory=sweep_catching)  # the catching case's loop
    cases: tuple[Literal["probe", "catching"], ...] = ("probe", "catching")
    steps: int = 1000  # horizon [samples of 1 ms]
    batch: int = 1  # pendulum conditions (vmap)
    repeat: int = 5  # timed calls per row (the shortest counts)
    skip: tuple[str, ...] = ()  # gradient variants to skip, by name (e.g. "implicit+remat")
    float32: bool = False  # float32 (default float64)

    def __post_init__(self):
        require(self, "count", "steps", "batch", "repeat")
        require(self, "given", "cases")


@command
def main(argv=None):
    """Runs the benchmark on the flags in ``argv`` (None: the command line); returns its rows."""
    cfg = parse(GradientsBenchmark(), argv, __doc__)
    dtype = bench.float_dtype(cfg.float32)
    enable_compile_cache()
    dev = jax.devices()[0]
    print(
        f"device: {dev.platform} {dev.device_kind}, dtype {jnp.dtype(dtype).name}, horizon "
        f"{cfg.steps} steps ({cfg.steps * 1e-3:.1f} s), batch {cfg.batch}"
    )
    rows = []
    for case in cfg.cases:
        forward, grads, args = bench.GRADIENT_CASES[case](cfg.task, cfg.steps, cfg.batch, dtype)
        fns = {"forward (rollout)": forward}
        fns.update({f"value_and_grad {k}": v for k, v in grads.items() if k not in cfg.skip})
        compile_s, finite = {}, {}
        for name, fn in fns.items():
            out, compile_s[name] = bench.first_call(fn, *args)
            finite[name] = bench.all_finite(out)
        times = bench.interleaved_best(fns, args, cfg.repeat)
        t_fwd = times["forward (rollout)"]
        for name, t in times.items():
            rows.append((case, name, t, t / t_fwd, compile_s[name], finite[name]))
            print(f"  {case:9s} {name:44s} {t * 1e3:9.1f} ms  x{t / t_fwd:5.2f}", flush=True)
    print()
    header = ["case", "computation", "time [ms]", "/ forward", "compile [s]", "finite"]
    cells = [(c, n, f"{t * 1e3:.1f}", f"{r:.2f}", f"{s:.1f}", f) for c, n, t, r, s, f in rows]
    lines = markdown_table(header, cells)
    lines[1] = "|---|---|---:|---:|---:|---|"  # numbers right-aligned
    print("\n".join(lines))
    return rows


if __name__ == "__main__":
    main()
