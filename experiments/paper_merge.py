"""Merges run folders of ``experiments/paper.py`` that ran disjoint arms of one preset.

E.g. one process per group of arms on a GPU machine (``scripts/gpu_paper.sh``), into one table:

    python experiments/paper_merge.py --runs runs/gpu/catching_paper-0 runs/gpu/catching_paper-1 \
        --out runs/catching_paper

Refuses runs of different presets, precision or protocol, different pendulums, or an arm in two
runs. Writes ``table.md`` and ``metrics.json``; ``config.json`` names the source runs.
"""

from hec_jax.loop.paper_report import merge_main

main = merge_main

if __name__ == "__main__":
    merge_main(doc=__doc__)
