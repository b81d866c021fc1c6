"""Step force on the hand (no object): simulated response against the target impedance (Eq. 40).

    python experiments/impedance_response.py --out runs/impedance_response --seed 0

The force (``--force`` [N] from ``--t-step`` [s], in a direction of the task plane drawn from
``--seed``) is applied on the hand body (``xfrc_applied``) and the controller uses exactly that
force as F_int; the pendulum hangs at rest 0.3 m away. The target impedance and the controller
are the task presets' (``hec_jax.loop.config``); every field is a flag (``--help``). The reference
``x_target`` is the exact solution of Eq. 40 under the simulator's zero-order hold (matrix
exponential, ``hec_jax.loop.plain.zoh_reference``), independent of the controller. Writes
``config.json``, ``metrics.json`` (relative RMS error per axis, saturation, timing),
``trajectory.npz`` (t, x_e, xd_e, x_d, f_ext, f_int, x_target, tau) and ``response.png``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from hec_jax.cli import command, parse, require
from hec_jax.control import ControllerConfig
from hec_jax.loop import TargetImpedance, catching
from hec_jax.mjx_scene import PendulumConfig


@dataclass(frozen=True)
class ResponseRun:
    """A step force on the hand, the impedance it should realise, and the run folder."""

    impedance: TargetImpedance = field(default_factory=lambda: catching().task.impedance)
    controller: ControllerConfig = field(default_factory=lambda: catching().task.controller)
    # the pendulum hangs at rest (release angle 0), 0.3 m from the hand: no contact
    pendulum: PendulumConfig = field(default_factory=lambda: PendulumConfig(release_angle=0.0))
    force: float = 10.0  # [N] step magnitude
    t_step: float = 0.1  # [s] time of the step
    duration: float = 1.5  # [s]
    out: Path = Path("runs/impedance_response")  # run folder
    overwrite: bool = False  # replace an existing non-empty out (else refused up front)
    seed: int = 0  # draws the step's direction in the task plane (x, z)

    def __post_init__(self):
        require(self, "positive", "force", "duration")
        require(self, "non_negative", "t_step")
        require(self, "seed", "seed")
        if not self.t_step < self.duration:
            raise ValueError(
                f"--t-step ({self.t_step}) must come before --duration ({self.duration})"
            )


@command
def main(argv=None) -> dict:
    """Runs the step response, writes the run folder; returns the metrics."""
    run = parse(ResponseRun(), argv, __doc__)
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from hec_jax.control import impedance_params, virtual_params
    from hec_jax.loop.plain import make_plain_run, plain_scene, zoh_reference
    from hec_jax.mjx_scene import TASK_AXES
    from hec_jax.report import timed
    from hec_jax.runs import run_folder, save_figure, write_json, write_npz

    settings = {k: v for k, v in dataclasses.asdict(run).items() if k != "seed"}
    with run_folder(
        run.out, run.seed, dict(settings, experiment="impedance_response"), run.overwrite
    ) as folder:
        angle = np.random.default_rng(run.seed).uniform(0, 2 * np.pi)
        direction = np.array([np.cos(angle), np.sin(angle)])  # in the task plane (x, z)
        scene = plain_scene()
        dt = scene.ids.timestep
        n = int(round(run.duration / dt))
        t = np.arange(n) * dt
        f_ext = np.zeros((n, 3))
        on = t >= run.t_step
        f_ext[on, 0], f_ext[on, 2] = run.force * direction[0], run.force * direction[1]
        imp = run.impedance
        params = impedance_params(imp.m_e, imp.b_e, imp.k_e)
        vparams = virtual_params(0.0, 0.0, 0.0, 0.25)  # F_o = 0: plain impedance control
        cond = run.pendulum.conditions()
        fn = jax.jit(make_plain_run(scene, run.controller))
        compiled, t_compile = timed(
            lambda: fn.lower(params, vparams, cond, jnp.asarray(f_ext)).compile()
        )
        (traj, x_d), t_run = timed(
            lambda: jax.block_until_ready(compiled(params, vparams, cond, jnp.asarray(f_ext)))
        )
        print(f"compile {t_compile:.1f} s, run {t_run:.3f} s ({n} steps)")

        traj, x_d = jax.tree.map(np.asarray, traj), np.asarray(x_d)
        x_e = traj.aux["x_e"]
        f_task = f_ext[:, list(TASK_AXES)]
        ref = np.stack(
            [
                zoh_reference(imp.m_e[a], imp.b_e[a], imp.k_e[a], f_task[:, a], dt)[:, 0]
                for a in (0, 1)
            ],
            axis=1,
        )
        dx = x_e - x_d[None, :]
        rel_rms = np.sqrt(np.mean((dx - ref) ** 2, axis=0)) / np.sqrt(np.mean(ref**2, axis=0))
        print("relative RMS error per axis (x, z):", rel_rms)
        if not np.all(np.isfinite(rel_rms)):  # a diverged run is a failed run (status, exit code)
            raise SystemExit(f"the closed loop diverged: relative RMS error {rel_rms}")
        metrics = dict(
            force_direction_xz=direction.tolist(),
            dt=dt,
            task_axes="(x, z) of the world frame",
            relative_rms_error_xz=rel_rms.tolist(),
            saturated=bool(traj.aux["saturated"].any()),
            compile_s=t_compile,
            run_s=t_run,
        )
        write_json(folder / "metrics.json", metrics)
        write_npz(
            folder / "trajectory.npz",
            t=t,
            x_e=x_e,
            xd_e=traj.aux["xd_e"],
            x_d=x_d,
            f_ext=f_task,
            f_int=traj.f_int[:, list(TASK_AXES)],
            x_target=ref + x_d[None, :],
            tau=traj.ctrl,
        )
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
        for a, name in enumerate("xz"):
            axes[a].plot(t, dx[:, a] * 1e3, label="simulated (MJX)")
            axes[a].plot(t, ref[:, a] * 1e3, "--", label="target impedance (Eq. 40)")
            axes[a].set_ylabel(f"d{name} [mm]")
            axes[a].legend(loc="lower right")
        axes[2].plot(t, f_task[:, 0], label="F_x")
        axes[2].plot(t, f_task[:, 1], label="F_z")
        axes[2].set(ylabel="F_ext [N]", xlabel="t [s]")
        axes[2].legend()
        fig.suptitle(
            f"M_e={imp.m_e}, B_e={imp.b_e}, K_e={imp.k_e}; rel. RMS err {rel_rms.round(4)}"
        )
        save_figure(fig, folder / "response.png")
        plt.close(fig)
        print(f"wrote {folder}")
        return metrics


if __name__ == "__main__":
    main()
