"""Catching (Sec. 6.2, Eqs. 59-62, Fig. 6): the hand learns to meet the swinging cube softly.

    python experiments/catching.py --out runs/catching --seed 0 [--eye truth|camera|paper] [--swings 15]

Conditions: ``plain`` (F_o = 0), ``frozen`` (the initial networks, no learning) and ``learned``
(online learning over successive swings, weights carried over; metrics on the last swing), for
``--seeds`` network initialisations side by side. The set-up and every default are the
``catching`` preset's (``hec_jax.loop.config.catching``, where each choice is argued); every
field of it is a flag (``--help``). Writes ``config.json``, ``metrics.json``,
``trajectory_<condition>.npz``, ``fig6_catching.png``, ``virtual_impedance.png``,
``peak_force_per_swing.png`` and, with ``--eye camera`` (the box tracker) or ``--eye paper``
(the paper's two-frame method, Eqs. 1-38), ``hand_eye.mp4``. The camera sees the lab scene
through a simulated industrial camera by default; ``--scene void --camera-model perfect`` is
the black void seen by a perfect camera (the default before 2026-11-26).
"""

from __future__ import annotations

from hec_jax.loop.cli import main_for


def main(argv=None) -> dict:
    """Runs the catching experiment (flags: ``--help``); returns its metrics."""
    return main_for("catching", __doc__, argv)


if __name__ == "__main__":
    main()
