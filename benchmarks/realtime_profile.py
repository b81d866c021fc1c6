"""Where a control tick's time goes, measured so that the machine's other load barely enters.

    python benchmarks/realtime_profile.py --rt-priority 50 --pin-cpus

Runs the real-time loop's own code (:func:`~hec_jax.realtime.runner.run_loop` on the MuJoCo C
plant: catching with the ground-truth eye, learning on) without deadlines, twice:

* **hot**: tick after tick, nothing in between (caches and branch predictors warm);
* **after idle**: before every tick the loop waits ``--idle-us`` as on the wall clock (sleep,
  then spin the last ``--spin-us``, :class:`~hec_jax.realtime.clock.WallClock`'s wait), so
  whatever else runs on the machine meanwhile cools the caches, as in a real-time run.

Per stage (plant read, observation, jitted step, plant write) it prints the control thread's
CPU time over the ticks (min and percentiles: time the thread ran, not time it waited for the
CPU), the CPU time of the process's other threads (XLA's pool, which runs parts of the jitted
step; a mean: the kernel updates other threads' times only at their context switches) and the
control thread's context switches. The minimum over the ticks is the work itself with the
least interference; the hot median adds what the step's own memory traffic costs the rest; the
after-idle median adds what other processes leave in the caches. ``--async-dispatch`` measures
JAX's default CPU dispatch (the jitted call handed to another thread) instead of the inline
dispatch ``experiments/realtime.py`` sets.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass

from hec_jax.cli import command, parse, require


@dataclass(frozen=True)
class TickProfile:
    """What the tick profiler measures (catching, ground-truth eye, learning on)."""

    ticks: int = 3000  # ticks per measurement
    idle_us: float = 800.0  # [us] wait before each tick ("after idle")
    spin_us: float = 200.0  # [us] of that wait spun rather than slept
    rt_priority: int = 0  # SCHED_FIFO priority of the loop (root); 0: none
    # [us] CPU wake-up latency asked of the kernel while measuring (PM QoS, root; 0: idle CPUs
    # poll instead of halting); None: nothing asked
    cpu_latency_us: int | None = None
    pin_cpus: bool = False  # the process on its first CPU while it runs
    # with rt_priority 0: the process's other threads (XLA's pool) under SCHED_IDLE while it
    # runs (``RealtimeConfig.pool_idle``; the real-time run does so with pin_cpus)
    pool_idle: bool = False
    async_dispatch: bool = False  # JAX's default CPU dispatch (default: inline)
    float32: bool = False  # float32 (default float64)

    def __post_init__(self):
        require(self, "count", "ticks")
        require(self, "non_negative", "idle_us", "spin_us", "rt_priority")


@command
def main(argv=None) -> dict:
    """Parses ``argv``, runs the measurement, prints the tables; returns the numbers."""
    args = parse(TickProfile(), argv, __doc__)

    import jax

    jax.config.update("jax_enable_x64", not args.float32)
    jax.config.update("jax_cpu_enable_async_dispatch", args.async_dispatch)
    from hec_jax import loop as L
    from hec_jax.realtime.clock import FreeClock, cpu_latency_request, realtime_priority
    from hec_jax.realtime.plant import ArmModel, MujocoPlant, plant_model
    from hec_jax.realtime.profile import IdleClock, stage_table
    from hec_jax.realtime.runner import make_step_fns, run_loop
    from hec_jax.runs import enable_compile_cache

    enable_compile_cache()
    exp = L.catching(eye="truth", seeds=1)
    loop = L.build_loop(exp.task)
    key = jax.random.split(jax.random.PRNGKey(0), 1)[0]
    plant = MujocoPlant(exp.task, loop.q_home)
    arm = ArmModel(plant_model(exp.task), loop.ids)
    ls = loop.learner_init(key, jax.numpy.float64 if not args.float32 else jax.numpy.float32)
    fns = make_step_fns(loop, ls, L.switches("learned"))

    def run(clock, steps):
        return run_loop(loop, plant, clock, key, "learned", steps, arm, fns=fns)

    run(FreeClock(), [200])  # compiled and warm
    cpus = {sorted(os.sched_getaffinity(0))[0]} if args.pin_cpus else None
    if cpus:
        from hec_jax.realtime.clock import pinned
    else:

        def pinned(_):
            return contextlib.nullcontext()

    results = {}
    latency = cpu_latency_request(args.cpu_latency_us)
    with pinned(cpus), realtime_priority(args.rt_priority, args.pool_idle), latency:
        for name, clock in (
            ("hot", FreeClock()),
            ("after idle", IdleClock(args.idle_us * 1e-6, args.spin_us * 1e-6)),
        ):
            results[name] = stage_table(run(clock, [args.ticks]).ticks)
    print(
        f"load average {os.getloadavg()}; async dispatch {args.async_dispatch}; "
        f"rt priority {args.rt_priority}; pool idle {args.pool_idle}; pinned {cpus}; "
        f"cpu latency {args.cpu_latency_us} us; "
        f"float{'32' if args.float32 else '64'}"
    )
    for name in ("hot", "after idle"):
        tab = results[name]
        print(f"\n{name}: control thread CPU per tick [us] (min / p50 / p90 / p99)")
        for stage in ("read", "observe", "step", "write", "tick"):
            q = tab[stage]
            print(f"  {stage:14s} {q['min']:7.1f} {q['p50']:7.1f} {q['p90']:7.1f} {q['p99']:7.1f}")
        print(f"  other threads' CPU per tick (mean) {tab['other_threads']['mean']:.1f} us")
        sv, si = tab["switches_voluntary"]["mean"], tab["switches_involuntary"]["mean"]
        print(f"  context switches per tick: {sv:.2f} voluntary, {si:.2f} involuntary")
    return results


if __name__ == "__main__":
    main()
