"""The paper's dE/dF_act and dE/dw (Eqs. 54-58) against exact ones through MJX (float64).

    python experiments/gradients.py --out runs/gradients --seed 0
    python experiments/gradients.py --out runs/gradients_horizon --swings 5 --horizons 1 10 50 200

Eqs. 55-58 treat the hand as a unit mass over one sample: dX_e/dF_act = dt^2 I and
dX_e'/dF_act = dt I. The exact one-step Jacobian d(X_e, X_e')(t + dt) / dF_act(t) is taken by
forward mode through one full control step (observation, impedance law with F_act = F_o as in
Eq. 48, torque saturation, MJX constraint solve, semi-implicit Euler; ``hec_jax.loop.exact``).

Without ``--horizons``: along the last of ``--swings`` learning swings of catching (the
``sweep_catching`` task, hand at X_HOME, default pendulum, one seed), at every ``--stride``-th
sample inside the virtual sphere, the Jacobian's error and, with the catching energy's gradient at
that state, the cosine and magnitude ratio of the paper's dE/dF_act to the exact one, split into
approach, contact and after contact; the Jacobian is checked against central differences at 4
samples. Writes ``metrics.json``, ``samples.npz`` and ``one_step_gradients.png``.

With ``--horizons H ...``: per task of ``--tasks`` (catching as above; hitting: the ``hitting``
preset) ``--swings`` swings of online learning, then one swing with the weights frozen; the
one-step comparison along it under each of ``--conditions``, and under the default conditions the
exact d/dw sum_{j=1..H} E (reverse mode through the closed loop with the implicit contact solve)
against the paper's rule summed over the same H samples, from ``--per-phase`` states per phase,
checked against float64 central differences (``hec_jax.loop.gradients``). Writes
``metrics.json``, ``samples.npz``, ``table.md``, ``one_step_sweep.png`` and ``horizons.png``.
Both write ``config.json``; results and their reading: docs/gradients.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from hec_jax.cli import command, parse, require

Condition = Literal["default", "rod_0.57", "cube_0.9kg", "release_-0.6"]


@dataclass(frozen=True)
class GradientsRun:
    """Which comparison, its sampling, and the run folder."""

    swings: int = 10  # learning swings (one step: the last is sampled; horizons: then a frozen one)
    stride: int = 2  # one step: every stride-th sample inside the sphere
    horizons: tuple[int, ...] = ()  # H [samples]; empty: the one-step comparison along catching
    tasks: tuple[Literal["catching", "hitting"], ...] = ("catching", "hitting")  # with horizons
    conditions: tuple[Condition, ...] = ("default", "rod_0.57", "cube_0.9kg", "release_-0.6")
    per_phase: int = 3  # horizon states per phase of the frozen swing
    out: Path = Path("runs/gradients")  # run folder
    overwrite: bool = False  # replace an existing non-empty out (else refused up front)
    seed: int = 0  # network initialisation (and the central differences' random direction)

    def __post_init__(self):
        require(self, "count", "swings", "stride", "per_phase")
        require(self, "given", "tasks", "conditions")
        if self.horizons:
            require(self, "count", "horizons")
        require(self, "seed", "seed")


@command
def main(argv=None) -> dict:
    """Runs the comparison and writes the run folder; returns the metrics."""
    run = parse(GradientsRun(), argv, __doc__)
    import jax

    jax.config.update("jax_enable_x64", True)
    import time

    import numpy as np

    from hec_jax.loop import build_loop, hitting, replace, sweep_catching
    from hec_jax.loop import gradients as gr
    from hec_jax.loop import gradients_report as report
    from hec_jax.mjx_scene import load_mj_model
    from hec_jax.runs import enable_compile_cache, run_folder, write_json, write_npz, write_text

    enable_compile_cache()
    settings = {k: v for k, v in dataclasses.asdict(run).items() if k != "seed"}
    with run_folder(run.out, run.seed, settings, run.overwrite) as folder:
        presets = {"catching": sweep_catching(), "hitting": hitting().task}
        tasks = {name: replace(presets[name], swings=run.swings) for name in run.tasks}
        if run.horizons:
            metrics, one_step_all, horizon_all = gr.horizon_comparison(
                tasks, run.conditions, run.seed, run.stride, run.horizons, run.per_phase
            )
            table = report.horizon_table(metrics, run.stride, one_step_all, horizon_all)
            write_text(folder / "table.md", table)
            write_json(folder / "metrics.json", metrics)
            write_npz(folder / "samples.npz", **report.horizon_arrays(one_step_all, horizon_all))
            dt = float(load_mj_model().opt.timestep)
            report.horizon_figures(folder, one_step_all, horizon_all, metrics["horizons"], dt)
            print(table)
            print(f"run folder: {folder}")
            return metrics

        t0 = time.perf_counter()
        loop = build_loop(tasks["catching"])
        res = gr.one_step_along_learning(loop, jax.random.PRNGKey(run.seed), run.stride)
        metrics = {
            "samples": int(len(res["step"])),
            "wall_s": time.perf_counter() - t0,
            "finite": bool(np.all(np.isfinite(res["exact"]))),
            "autodiff_vs_central_differences_max_rel_err": max(res["fd_err"]),
            **gr.phase_summary(res),
        }
        write_json(folder / "metrics.json", metrics)
        arrays = ("step", "phase", "exact", "cosine", "ratio", "jac_rel_err")
        paper = gr.unit_mass_jacobian(loop.ids.timestep)
        write_npz(folder / "samples.npz", paper=paper, **{k: res[k] for k in arrays})
        report.one_step_figure(folder, res, loop.ids.timestep)
        print(f"run folder: {folder}")
        for name in gr.PHASES:
            if name in metrics:
                print(name, metrics[name])
        return metrics


if __name__ == "__main__":
    main()
