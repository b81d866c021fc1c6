"""The paper's experiments as the paper means them (Sec. 6): one table per call.

    python experiments/paper.py --preset catching_paper --out runs/catching_paper
    python experiments/paper.py --preset hitting_paper --reduced --out runs/hitting_paper_cpu

Runs the paper preset of the task (``hec_jax.loop.config.catching_paper`` / ``hitting_paper``)
under the protocol of ``hec_jax.loop.protocol`` (training swings with the pendulum drawn per
swing, held-out pendulums for the numbers) for every arm, baseline and ablation of
``hec_jax.loop.arms``; writes ``table.md``, ``metrics.json``, ``learning_curves.png`` and a
Fig. 6/7-style panel. ``--reduced``: a version for a 2-core CPU. Results: docs/experiments.md.
"""

from hec_jax.loop.paper_report import paper_main

if __name__ == "__main__":
    paper_main(doc=__doc__)
