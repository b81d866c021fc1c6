"""The pendulum swings into the virtual sphere (Eqs. 45-48): the hand retreats before contact.

    python experiments/avoidance.py --out runs/avoidance --seed 0

Two runs in one vmapped rollout: non-contact impedance (fixed K_o, B_o, M_o, projected onto the
stable set of Eq. 49) and plain impedance (F_o = 0). The seed draws the release angle from
``--release-range`` (the 0.45-0.6 rad of docs/paper_readings.md, parameter values); the target
impedance is the task presets' (``hec_jax.loop.config``); every field is a flag (``--help``).
Writes ``config.json``, ``metrics.json`` (first contact, peak force, hand retreat, closest
distance per run), ``trajectory.npz`` (t, x_e, xd_e, x_o, f_o, f_int, rho per run) and
``avoidance.png``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from hec_jax.cli import command, parse, require
from hec_jax.control import ControllerConfig
from hec_jax.loop import TargetImpedance, catching

RUNS = ("virtual_sphere", "plain")


@dataclass(frozen=True)
class AvoidanceRun:
    """The fixed virtual impedance, the target impedance, the swing and the run folder."""

    impedance: TargetImpedance = field(default_factory=lambda: catching().task.impedance)
    controller: ControllerConfig = field(default_factory=lambda: catching().task.controller)
    k_o: float = 400.0  # [N/m] virtual stiffness
    b_o: float = 20.0  # [N s/m] virtual viscosity
    m_o: float = 0.0  # [kg] virtual inertia
    radius: float = 0.25  # [m] virtual sphere radius r
    release_range: tuple[float, float] = (0.45, 0.6)  # [rad] |release angle| drawn from this
    duration: float = 1.5  # [s]
    out: Path = Path("runs/avoidance")  # run folder
    overwrite: bool = False  # replace an existing non-empty out (else refused up front)
    seed: int = 0  # draws the release angle

    def __post_init__(self):
        require(self, "non_negative", "k_o", "b_o", "m_o")
        require(self, "positive", "radius", "duration")
        require(self, "seed", "seed")
        lo, hi = self.release_range
        if not (0 <= lo <= hi and hi < math.pi):
            raise ValueError(
                f"--release-range must be 0 <= low <= high < pi, got {self.release_range}"
            )


@command
def main(argv=None) -> dict:
    """Runs both swings, writes the run folder; returns the metrics."""
    run = parse(AvoidanceRun(), argv, __doc__)
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from hec_jax.control import impedance_params, project_stable, virtual_params
    from hec_jax.loop.plain import contact_summary, make_plain_run, plain_scene
    from hec_jax.mjx_scene import TASK_AXES, default_conditions
    from hec_jax.report import timed
    from hec_jax.runs import run_folder, save_figure, write_json, write_npz

    release = -float(np.random.default_rng(run.seed).uniform(*run.release_range))
    cond = default_conditions(release_angle=release)
    settings = {k: v for k, v in dataclasses.asdict(run).items() if k != "seed"}
    settings.update(experiment="avoidance", release_angle=release, conditions=cond._asdict())
    with run_folder(run.out, run.seed, settings, run.overwrite) as folder:
        scene = plain_scene()
        dt = scene.ids.timestep
        n = int(round(run.duration / dt))
        imp = run.impedance
        params = impedance_params(imp.m_e, imp.b_e, imp.k_e)
        vp_on = virtual_params(run.m_o, run.b_o, run.k_o, run.radius)
        vp_on = project_stable(vp_on, params.m_e, params.b_e, params.k_e)  # Eq. 49
        vp_off = virtual_params(0.0, 0.0, 0.0, run.radius)
        vps = jax.tree.map(lambda a, b: jnp.stack([a, b]), vp_on, vp_off)
        plain_run = make_plain_run(scene, run.controller)
        fn = jax.jit(jax.vmap(lambda vp: plain_run(params, vp, cond, jnp.zeros((n, 3)))[0]))
        compiled, t_compile = timed(lambda: fn.lower(vps).compile())
        traj, t_run = timed(lambda: jax.tree.map(np.asarray, jax.block_until_ready(compiled(vps))))
        print(f"compile {t_compile:.1f} s, run {t_run:.3f} s (2 x {n} steps)")

        t = np.arange(n) * dt
        summary = {
            name: contact_summary(jax.tree.map(lambda x, i=i: x[i], traj), t)
            for i, name in enumerate(RUNS)
        }
        print(summary)
        write_json(
            folder / "metrics.json",
            dict(summary, m_o=vp_on.m_o, b_o=vp_on.b_o, k_o=vp_on.k_o, dt=dt, compile_s=t_compile,
                 run_s=t_run),
        )  # fmt: skip
        write_npz(
            folder / "trajectory.npz",
            t=t,
            x_e=traj.aux["x_e"],
            xd_e=traj.aux["xd_e"],
            x_o=traj.aux["x_o"],
            f_o=traj.aux["f_o"],
            f_int=traj.f_contact[:, :, list(TASK_AXES)],
            rho=traj.aux["rho"],
            run_names=np.array(RUNS),
        )
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
        for i, (name, ls) in enumerate((("virtual sphere", "-"), ("F_o = 0", "--"))):
            axes[0].plot(t, traj.aux["x_e"][i][:, 0], ls, label=f"hand x ({name})")
            axes[1].plot(t, traj.aux["rho"][i], ls, label=f"|X_r| ({name})")
            axes[2].plot(
                t, np.linalg.norm(traj.f_contact[i], axis=1), ls, label=f"|F_int| ({name})"
            )
        axes[0].plot(t, traj.aux["x_o"][1][:, 0], ":", label="cube x")
        axes[0].set_ylabel("x [m]")
        axes[1].axhline(run.radius, color="k", lw=0.5, label="r")
        axes[1].set_ylabel("distance [m]")
        axes[2].set(ylabel="contact force [N]", xlabel="t [s]")
        for a in axes:
            a.legend(fontsize=8)
        save_figure(fig, folder / "avoidance.png")
        plt.close(fig)
        print(f"wrote {folder}")
        return summary


if __name__ == "__main__":
    main()
