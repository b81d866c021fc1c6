"""Hitting (Sec. 6.3, Eqs. 63-66, Fig. 7): the hand learns to strike the swinging cube periodically.

    python experiments/hitting.py --out runs/hitting --seed 0 [--eye truth|camera|paper]

Protocol: ``--swings`` training swings from the same release (the world restarts each swing, the
learner's weights carry over), then one continuous run of ``--final-s`` seconds (the pendulum
released once, never reset) with online learning going on; hits are counted in that run
(``hec_jax.loop.metrics.hit_series``: a hit is a contact episode, episodes less than 50 ms apart
merged; periodic: start-to-start intervals within 20% of their median; bounded pulses: none above
the series' first, each under 50 ms). The set-up and every default are the ``hitting`` preset's
(``hec_jax.loop.config.hitting``: the hitting pad, mu); every field is a flag (``--help``).
Writes ``config.json``, ``metrics.json``, ``trajectory_<condition>.npz`` (the continuous run),
``fig7_hitting.png``, ``gain_beta.png`` and, with ``--eye camera`` or ``--eye paper``,
``hand_eye.mp4``. The camera sees the lab scene through a simulated industrial camera by
default; ``--scene void --camera-model perfect`` is the earlier black void and perfect camera.
"""

from __future__ import annotations

from hec_jax.loop.cli import main_for


def main(argv=None) -> dict:
    """Runs the hitting experiment (flags: ``--help``); returns its metrics."""
    return main_for("hitting", __doc__, argv)


if __name__ == "__main__":
    main()
