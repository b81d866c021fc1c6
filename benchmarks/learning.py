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

The task is the catching sweep's (``hec_jax.loop.sweep_catching``; its flags below), its pendulum
released once; the task's swings and durations are not used (one rollout of ``--steps``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp

from hec_jax import benchmarking as bench
from hec_jax.cli import command, parse, require
from hec_jax.loop import TaskConfig, build_loop, sweep_catching
from hec_jax.report import markdown_table
from hec_jax.runs import run_folder, write_json, write_text

LATENCY_ROWS = {  # metrics key: row of the latency table
    "control_and_learning": "control + learning on an observation (Eqs. 52-58, 41-47)",
    "control_only": "control only on an observation (Eqs. 41-47)",
    "control_and_learning_with_observe": "control + learning incl. observation from the MJX state",
    "control_only_with_observe": "control only incl. observation from the MJX state",
}
RATE_HEADER = (
    "batch",
    "learning rollout [steps/s]",
    "forward-only rollout [steps/s]",
    "ratio",
    "compile learning [s]",
)


@dataclass(frozen=True)
class LearningBenchmark:
    """The learning benchmark: the task, rollout length, batches and repeats."""

    task: TaskConfig = field(default_factory=sweep_catching)
    out: Path = Path("runs/bench_learning")  # run folder (written complete or not at all)
    overwrite: bool = False  # replace an existing non-empty --out (else refused up front)
    seed: int = 0  # PRNG seed of the network initialisations (and the release perturbations)
    steps: int = 500  # control steps per rollout
    batches: tuple[int, ...] = (1, 16, 128)  # vmapped rollouts, one row each
    repeats: int = 2000  # calls for the latency timing
    float32: bool = False  # float32 (default float64)

    def __post_init__(self):
        require(self, "count", "steps", "batches", "repeats")
        require(self, "seed", "seed")


def measure(cfg: LearningBenchmark, dtype) -> tuple[dict, list]:
    """({row: latency [s]}, [(batch, {rollout: (steps/s, compile [s])})]) of one run."""
    loop = build_loop(cfg.task)
    conditions = cfg.task.pendulum.conditions()
    key = jax.random.PRNGKey(cfg.seed)
    steps = bench.learning_steps(loop, conditions, key, dtype)
    lat = {name: bench.mean_call(fn, args, cfg.repeats) for name, (fn, args) in steps.items()}
    rollouts = bench.learning_rollouts(loop, conditions, cfg.steps, dtype)
    rows = []
    for batch in cfg.batches:
        keys = jax.random.split(key, batch)
        rates = {}
        for name, fn in rollouts.items():
            run = jax.jit(jax.vmap(fn))
            _, compile_s = bench.first_call(run, keys)
            rates[name] = (batch * cfg.steps / bench.mean_call(run, (keys,), 2), compile_s)
        rows.append((batch, rates))
        print(
            f"batch {batch}: learning {rates['learning'][0]:.3g} steps/s, forward-only "
            f"{rates['forward_only'][0]:.3g} steps/s",
            flush=True,
        )
    return lat, rows


@command
def main(argv=None):
    """Runs the benchmark on the flags in ``argv`` (None: the command line); returns metrics."""
    cfg = parse(LearningBenchmark(), argv, __doc__)
    dtype = bench.float_dtype(cfg.float32)
    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("seed", "overwrite")}
    with run_folder(cfg.out, cfg.seed, settings, cfg.overwrite) as folder:
        lat, rows = measure(cfg, dtype)
        us = {k: v * 1e6 for k, v in lat.items()}
        lat_rows = [[what, f"{us[k]:.1f}"] for k, what in LATENCY_ROWS.items()]
        ratio = lat["control_and_learning"] / lat["control_only"]
        lat_rows.insert(2, ["ratio learning / control only", f"{ratio:.2f}"])
        rate_rows = []
        for b, r in rows:
            learn, fwd, compile_s = r["learning"][0], r["forward_only"][0], r["learning"][1]
            rate_rows.append(
                (b, f"{learn:.3g}", f"{fwd:.3g}", f"{learn / fwd:.2f}", f"{compile_s:.1f}")
            )
        lines = [
            f"Device: {jax.devices()[0]} ({jax.default_backend()}), {jnp.dtype(dtype).name}, "
            f"{cfg.steps}-step rollouts.",
            "",
            *markdown_table(["one jitted step", "latency [us]"], lat_rows),
            "",
            *markdown_table(RATE_HEADER, rate_rows),
        ]
        text = "\n".join(lines) + "\n"
        metrics = {
            "latency_us": us,
            "latency_target_100us_met": bool(lat["control_and_learning"] <= 100e-6),
            "throughput_steps_per_s": {
                str(b): {name: rate for name, (rate, _) in r.items()} for b, r in rows
            },
        }
        write_json(folder / "metrics.json", metrics)
        write_text(folder / "table.md", text)
    print(text)
    return metrics


if __name__ == "__main__":
    main()
