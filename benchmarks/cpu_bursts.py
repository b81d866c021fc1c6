"""Bursts of CPU work on one CPU, as another process on a real-time loop's CPU would make them.

    python benchmarks/cpu_bursts.py --cpu 0 --burst-ms 60 --every-s 2 --seconds 40 &
    python experiments/realtime.py --preset catching --eye truth --duration-s 15 --twin none --spin-us 1000 --pool-idle

Pins itself to ``--cpu`` and spins ``--burst-ms`` of every ``--every-s`` (the burst, then the
sleep) for ``--seconds``, at normal scheduling: the disturbance that
``RealtimeConfig.pool_idle`` turns into a stall of the whole burst (docs/realtime.md, "XLA's
pool under SCHED_IDLE"). Prints nothing; returns the number of bursts.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from hec_jax.cli import command, parse, require


@dataclass(frozen=True)
class Bursts:
    """Where and how often to burn the CPU."""

    cpu: int = 0  # the CPU to burn (os.sched_setaffinity)
    burst_ms: float = 60.0  # [ms] of spinning per burst
    every_s: float = 2.0  # [s] sleep after each burst
    seconds: float = 40.0  # [s] in all

    def __post_init__(self):
        require(self, "non_negative", "cpu")
        require(self, "positive", "burst_ms", "every_s", "seconds")


@command
def main(argv=None) -> int:
    """Parses ``argv`` and burns the CPU in bursts; returns the number of bursts."""
    args = parse(Bursts(), argv, __doc__)
    os.sched_setaffinity(0, {args.cpu})
    end, n = time.monotonic() + args.seconds, 0
    while time.monotonic() < end:
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.burst_ms * 1e-3:
            pass
        n += 1
        time.sleep(args.every_s)
    return n


if __name__ == "__main__":
    main()
