"""Episodic training of the virtual-impedance networks with exact gradients (BPTT + optax) across a
batch of pendulum conditions, against the paper's online rule (Eqs. 52-58).

    python experiments/train_bptt.py --out runs/train_bptt --seed 0 [--batch 6] [--swings 10]

Every arm starts from the same initial networks (``--seed``) and sees the same catching swings
(the ``sweep_catching`` task with 1 s swings; every field is a flag, ``--help``) of the same
``--batch`` pendulum conditions (rod length, cube mass, release angle drawn around the default so
that every swing reaches the waiting hand: ``hec_jax.loop.bptt.training_conditions``):

* **paper**: the online learner of ``hec_jax.nets`` (dE/dF_act of Eqs. 55-58, one weight update per
  sample inside the sphere), one run per condition (each condition learns its own networks), the
  weights carried over ``--swings`` swings (``hec_jax.loop.make_sweep``);
* **exact**: the same online learner with the exact one-step dE/dF_act through an MJX step
  (``hec_jax.loop.exact``) instead of Eqs. 55-58;
* **bptt**: one set of networks for all conditions, frozen within a swing; after each swing of the
  whole batch one Adam step on the gradient of the swing's task energy, by reverse mode through
  the whole closed loop (``hec_jax.loop.bptt``); ``--swings`` steps.

Reports per swing the batch-mean peak contact force, swings to convergence (first swing after
which the batch-mean peak stays within 10% of its final value) and the final peak force against
plain impedance control (F_o = 0). Writes ``config.json``, ``metrics.json``, ``history.npz`` and
``peak_force_per_swing.png``. Results: docs/gradients.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from hec_jax.cli import command, parse, require
from hec_jax.loop import TaskConfig, replace, sweep_catching


@dataclass(frozen=True)
class TrainRun:
    """The task, the batch, the optimiser, the arms and the run folder."""

    task: TaskConfig = field(
        default_factory=lambda: replace(sweep_catching(), swing_s=1.0, swings=10)
    )
    batch: int = 6  # pendulum conditions
    lr: float = 3e-3  # Adam learning rate
    clip: float = 1.0  # global gradient-norm clip
    arms: tuple[Literal["paper", "exact", "bptt"], ...] = ("paper", "exact", "bptt")  # + plain
    float32: bool = False  # float32 (default float64)
    out: Path = Path("runs/train_bptt")  # run folder
    overwrite: bool = False  # replace an existing non-empty out (else refused up front)
    seed: int = 0  # network initialisation and the draw of the conditions

    def __post_init__(self):
        require(self, "count", "batch")
        require(self, "given", "arms")
        require(self, "positive", "lr", "clip")
        require(self, "seed", "seed")


@command
def main(argv=None) -> dict:
    """Runs the arms and writes the run folder; returns the metrics."""
    run = parse(TrainRun(), argv, __doc__)
    import jax

    jax.config.update("jax_enable_x64", not run.float32)
    import time

    import jax.numpy as jnp
    import numpy as np

    from hec_jax.loop import bptt, build_loop, make_sweep, switches
    from hec_jax.loop.exact import build_exact_loop
    from hec_jax.loop.metrics import force_norm, mean_std
    from hec_jax.runs import enable_compile_cache, run_folder, save_figure, write_json, write_npz

    enable_compile_cache()
    dtype = jnp.float32 if run.float32 else jnp.float64
    settings = {k: v for k, v in dataclasses.asdict(run).items() if k != "seed"}
    with run_folder(
        run.out, run.seed, dict(settings, task_name="catching"), run.overwrite
    ) as folder:
        conds = bptt.training_conditions(run.batch, run.seed, run.task.pendulum, dtype)
        key = jax.random.PRNGKey(run.seed)
        keys = jnp.broadcast_to(key, (run.batch, 2))
        t_start = time.perf_counter()
        loop = build_loop(run.task)
        sweep = jax.jit(make_sweep(loop))
        logs_plain, t_plain = bptt.timed_sweep(sweep, keys, switches("plain"), conds)
        peak_plain = force_norm(logs_plain).max(-1)[:, 0]  # (batch,)
        reach = peak_plain > 0  # ratios over plain only where the swing reaches the hand
        if not np.all(reach):
            print(f"warning: {int(np.sum(~reach))} swing(s) never reach the hand", flush=True)
        timing, online = {"plain": t_plain}, {}
        for arm in ("paper", "exact"):
            if arm in run.arms:
                fn = sweep if arm == "paper" else jax.jit(make_sweep(build_exact_loop(run.task)))
                online[arm], timing[arm] = bptt.timed_sweep(fn, keys, switches("learned"), conds)
                peaks = force_norm(online[arm]).max(-1).mean(0)  # batch mean per swing
                print(f"{arm}: batch-mean peak per swing {np.round(peaks, 1).tolist()}", flush=True)

        def progress(epoch, row):
            print(
                f"epoch {epoch:3d} loss {row['mean_loss']:.5f} peak {float(np.mean(row['peak'])):7.2f}"
                f" N |grad| {row['grad_norm']:.3g} finite {row['finite']}",
                flush=True,
            )

        metrics = {
            "batch": run.batch,
            "swings": run.task.swings,
            "plain_peak_force": mean_std(peak_plain),
            "conditions_reaching_hand": int(np.sum(reach)),
        }
        for arm, logs in online.items():
            metrics[arm] = bptt.online_metrics(logs, peak_plain, reach)
        curves = {f"peak_{a}": force_norm(lg).max(-1) for a, lg in online.items()}
        if "bptt" in run.arms:
            t0 = time.perf_counter()
            hist = bptt.train_bptt(loop, conds, key, dtype, run.lr, run.clip, progress)
            timing["bptt"] = time.perf_counter() - t0
            metrics["bptt"] = bptt.bptt_metrics(hist, peak_plain, reach)
            curves["peak_bptt"] = np.stack(hist["peak"], axis=1)
            curves["loss_bptt"] = np.stack(hist["loss"], axis=1)
        metrics["timing_s"] = {**timing, "total": time.perf_counter() - t_start}
        write_json(folder / "metrics.json", metrics)
        write_npz(folder / "history.npz", peak_plain=peak_plain, **curves)
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        labels = {
            "peak_paper": ("o-", "paper's rule (online, Eqs. 55-58)"),
            "peak_exact": ("^-", "online, exact one-step dE/dF_act"),
            "peak_bptt": ("s-", "BPTT + Adam, one set of nets"),
        }
        fig, ax = plt.subplots(figsize=(7, 4))
        for name, (fmt, label) in labels.items():
            if name in curves:
                c = curves[name]
                ax.errorbar(np.arange(1, c.shape[1] + 1), c.mean(0), c.std(0), fmt=fmt, label=label)
        ax.axhline(peak_plain.mean(), color="k", ls=":", label="plain impedance")
        ax.set(xlabel="swing", ylabel="peak |F_int| [N] (mean +- std over conditions)")
        ax.legend()
        fig.tight_layout()
        save_figure(fig, folder / "peak_force_per_swing.png")
        plt.close(fig)
        print(f"run folder: {folder}")
        for name in ("paper", "exact", "bptt"):
            if name in metrics:
                mm = metrics[name]
                print(
                    f"{name:6s} final peak {mm['final_peak_force']['mean']:6.1f} N "
                    f"({mm['final_over_plain']['mean']:.2f} of plain), "
                    f"swings to convergence {mm['swings_to_convergence']}"
                )
        return metrics


if __name__ == "__main__":
    main()
