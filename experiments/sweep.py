"""Sweep over pendulum conditions and seeds with the online learning inside (``vmap``).

    python experiments/sweep.py --out runs/sweep --seed 0
    python experiments/sweep.py --out runs/sweep --shard-index 0 --num-shards 4   # one of 4 hosts
    python experiments/sweep.py --out runs/sweep --merge-only                      # merge shards

The grid is the product of the listed values of each pendulum field (``--rod-lengths 0.5 0.6``,
``--cube-masses ...``, ``--release-angles ...``, ``--hinge-xs ...``), times ``--seeds`` network
initialisations; each run is the ``sweep_catching`` task (``hec_jax.loop.config``) plus the plain
baseline under the same condition. Chunks of ``--chunk`` runs are written atomically and skipped
on restart (same settings required); several devices split each chunk
(``hec_jax.loop.devices``). Writes ``config.json`` per shard, ``metrics.json`` (success rate,
peak force ratio learned/plain, diverged runs) and ``peak_ratio_map.png``.
"""

from __future__ import annotations

from hec_jax.loop.cli import sweep_main


def main(argv=None) -> dict:
    """Runs (or merges) the sweep (flags: ``--help``); returns the merged metrics."""
    return sweep_main(__doc__, argv)


if __name__ == "__main__":
    main()
