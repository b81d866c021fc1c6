"""How steady each CPU's speed is: the same small piece of work, timed again and again.

    python benchmarks/cpu_steadiness.py --seconds 60

Every ``--gap-s`` the process moves to the next CPU (round robin) and times ``--matmuls``
products of a fixed 200 x 200 float64 matrix (single-threaded BLAS) in its own CPU time, so
that time the host takes from the virtual CPU (steal) and other processes' turns do not count
(:func:`hec_jax.realtime.clock.probe_cpu_speed`). A machine whose CPUs run at one speed gives
the same time every time; a virtual CPU that shares a physical core or its clock with busy
neighbours runs slower while they run, and that shows here as a spread of the CPU time, not as
steal.

Prints, per CPU, the samples' min / p50 / p90 / max [ms] and max / min; returns them. The
real-time runs (``docs/realtime.md``) read it beside their deadline tables: an eye frame or a
control tick timed on such a CPU varies by the same factor.
"""

from __future__ import annotations

import os

# single-threaded BLAS before NumPy loads it (one CPU's speed at a time)
for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

from dataclasses import dataclass  # noqa: E402

from hec_jax.cli import command, parse, require  # noqa: E402


@dataclass(frozen=True)
class Steadiness:
    """What the probe measures."""

    seconds: float = 60.0  # [s] how long to sample
    gap_s: float = 0.5  # [s] sleep between samples (the CPU idles meanwhile)
    matmuls: int = 200  # 200 x 200 products per sample (~10 ms of one CPU)

    def __post_init__(self):
        require(self, "positive", "seconds")
        require(self, "non_negative", "gap_s")
        require(self, "count", "matmuls")


@command
def main(argv=None) -> dict:
    """Parses ``argv``, samples, prints the table; returns {cpu: summary}."""
    args = parse(Steadiness(), argv, __doc__)
    from hec_jax.realtime.clock import probe_cpu_speed

    out = probe_cpu_speed(args.seconds, args.gap_s, args.matmuls)
    print(f"CPU time of {args.matmuls} products of a 200 x 200 matrix [ms], {args.seconds:g} s")
    print("| CPU | samples | min | p50 | p90 | max | max / min |")
    print("|---|---|---|---|---|---|---|")
    for c, r in out.items():
        print(f"| {c} | {r['n']} | {r['min']:.1f} | {r['p50']:.1f} | {r['p90']:.1f} | "
              f"{r['max']:.1f} | {r['max_over_min']:.2f} |")  # fmt: skip
    return out


if __name__ == "__main__":
    main()
