"""How steady each CPU's speed is: the same small piece of work, timed again and again.

    python benchmarks/cpu_steadiness.py --seconds 60

Every ``--gap-s`` the process moves to the next CPU (round robin) and times ``--matmuls``
products of a fixed 200 x 200 float64 matrix (single-threaded BLAS) in its own CPU time, so
that time the host takes from the virtual CPU (steal) and other processes' turns do not count.
A machine whose CPUs run at one speed gives the same time every time; a virtual CPU that shares
a physical core with a busy neighbour (another VM on the sibling hyperthread) runs slower while
the neighbour runs, and that shows here as a spread of the CPU time, not as steal.

Prints, per CPU, the samples' min / p50 / p90 / max [ms] and max / min; returns them. The
real-time runs (``docs/realtime.md``) read it beside their deadline tables: an eye frame or a
control tick timed on such a CPU varies by the same factor.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from hec_jax.cli import command, parse, require

# single-threaded BLAS before NumPy loads it (one CPU's speed at a time)
for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")


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


def sample_cpu_ms(matmuls: int, a) -> float:
    """[ms] this thread's CPU time for ``matmuls`` products ``a @ a``."""
    import time

    t0 = time.thread_time()
    for _ in range(matmuls):
        a @ a
    return 1e3 * (time.thread_time() - t0)


def summarise(samples_ms) -> dict:
    """{"n", "min", "p50", "p90", "max", "max_over_min"} of the samples [ms].

    Raises:
        ValueError: no samples, or one not finite and > 0.
    """
    import numpy as np

    s = np.asarray(samples_ms, float)
    if s.size == 0 or not np.all(np.isfinite(s) & (s > 0)):
        raise ValueError(f"samples must be finite times > 0, got {samples_ms!r}")
    p = {k: float(np.percentile(s, q)) for k, q in (("p50", 50), ("p90", 90))}
    return {"n": int(s.size), "min": float(s.min()), **p, "max": float(s.max()),
            "max_over_min": float(s.max() / s.min())}  # fmt: skip


@command
def main(argv=None) -> dict:
    """Parses ``argv``, samples, prints the table; returns {cpu: summary}."""
    args = parse(Steadiness(), argv, __doc__)
    import time

    import numpy as np

    a = np.random.default_rng(0).random((200, 200))
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [None]
    old = set(cpus) if cpus != [None] else None
    samples: dict = {c: [] for c in cpus}
    t_end, i = time.monotonic() + args.seconds, 0
    try:
        while time.monotonic() < t_end:
            cpu = cpus[i % len(cpus)]
            if cpu is not None:
                os.sched_setaffinity(0, {cpu})
                time.sleep(0.001)  # let the move happen before the clock starts
            samples[cpu].append(sample_cpu_ms(args.matmuls, a))
            i += 1
            time.sleep(args.gap_s)
    finally:
        if old is not None:
            os.sched_setaffinity(0, old)
    out = {str(c): summarise(s) for c, s in samples.items() if s}
    print(f"CPU time of {args.matmuls} products of a 200 x 200 matrix [ms], {args.seconds:g} s")
    print("| CPU | samples | min | p50 | p90 | max | max / min |")
    print("|---|---|---|---|---|---|---|")
    for c, r in out.items():
        print(f"| {c} | {r['n']} | {r['min']:.1f} | {r['p50']:.1f} | {r['p90']:.1f} | "
              f"{r['max']:.1f} | {r['max_over_min']:.2f} |")  # fmt: skip
    return out


if __name__ == "__main__":
    main()
