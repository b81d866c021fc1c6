"""Run folders of experiments (NumPy boundary): trajectories, metrics, figures, video.

:func:`write_experiment` writes what :func:`~hec_jax.loop.experiment.run_experiment` returns into
a run folder made by :func:`hec_jax.runs.start_run`: ``metrics.json``,
``trajectory_<condition>.npz``, the task's figures (Fig. 6 / Fig. 7 style) and, for camera runs,
``hand_eye.mp4``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hec_jax.loop.experiment import ExperimentResult
from hec_jax.loop.metrics import force_norm
from hec_jax.nets import gain_alpha, gain_beta
from hec_jax.runs import save_figure, write_json, write_npz, write_video


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def diverged_seeds(logs: dict) -> dict:
    """{condition: seeds whose simulation went non-finite (hand position or contact force NaN or
    inf anywhere)}; ``logs`` as :attr:`ExperimentResult.logs` (a continuous run included).
    """
    out = {}
    for condition, lg in logs.items():
        parts = [lg, lg["final"]] if "final" in lg else [lg]
        bad = np.zeros(len(lg["x_e"]), bool)
        for part in parts:
            for key in ("x_e", "f_contact"):
                x = np.asarray(part[key])
                bad |= ~np.all(np.isfinite(x.reshape(len(x), -1)), axis=1)
        out[condition] = int(bad.sum())
    return out


def write_experiment(folder: Path, result: ExperimentResult) -> None:
    """Trajectories, ``metrics.json``, figures and (camera runs) the video of ``result``.

    ``metrics.json`` holds the metrics and ``diverged_seeds`` (:func:`diverged_seeds`); a value
    that is not finite (e.g. the peak force of a diverged seed) is written as null and named in
    ``non_finite_as_null`` (:func:`hec_jax.runs.write_json`).
    """
    final = result.config.task.final_s > 0
    logs = {c: lg["final"] for c, lg in result.logs.items()} if final else result.logs
    save_trajectories(folder, logs, result.dt)
    write_json(
        folder / "metrics.json", {**result.metrics, "diverged_seeds": diverged_seeds(result.logs)}
    )
    if result.config.task.learner.task == "hitting":
        hitting_figures(folder, result)
    else:
        catching_figures(folder, result)
    if result.video:
        fps = result.metrics["camera"]["eye"]["fps"]
        write_video(folder / "hand_eye.mp4", (f[..., ::-1] for f in result.video), fps)


def timing_line(timing: dict) -> str:
    """Compile time apart from run time, from ``metrics["timing_s"]`` [s]."""
    parts = []
    if "compile" in timing:
        parts.append(f"compile {timing['compile']:.1f} s")
    run = sum(timing.get(c, 0.0) for c in ("plain", "frozen", "learned"))
    parts.append(f"run {run:.1f} s")
    camera = sum(timing.get(f"{c}_camera", 0.0) for c in ("frozen", "learned"))
    if camera:
        parts.append(f"camera loop {camera:.1f} s")
    if "total" in timing:
        parts.append(f"total {timing['total']:.1f} s")
    return "time: " + ", ".join(parts)


def print_summary(result: ExperimentResult) -> None:
    """One line per condition, the eye's summary for camera runs, the targets and the time
    (compile apart).
    """
    m = result.metrics
    for c in ("plain", "frozen", "learned"):
        mc = m[c]
        if "periodic_hits" in mc:
            print(
                f"{c:8s} hits {mc['hits']['mean']:4.1f}, periodic {mc['periodic_hits']['mean']:4.1f}"
                f" (min {mc['min_periodic_hits_over_seeds']}), max pulse "
                f"{mc['peak_force']['mean']:6.1f} N, series pulses "
                f"{mc['series_pulse_max']['mean']:6.1f} -> {mc['series_pulse_last']['mean']:5.1f}"
                f" N, bounded {mc['pulses_bounded_every_seed']}"
            )
        else:
            print(
                f"{c:8s} peak force {mc['peak_force']['mean']:7.1f} +- "
                f"{mc['peak_force']['std']:5.1f} N, settle {mc['settle_force']['mean']:5.2f} +- "
                f"{mc['settle_force']['std']:4.2f} N, held every seed {mc['held_every_seed']}"
            )
    camera = m.get("camera")
    if camera:
        for condition, e in camera["eye"].items():
            if not isinstance(e, dict):
                continue
            print(
                f"eye {condition:14s} frames {e['frames']:5d} valid {e['frames_valid']:5d} "
                f"lost {e['tracks_lost']:3d}  position "
                f"{1e3 * e['controller_position_rms_m']:5.1f} mm velocity "
                f"{e['controller_velocity_rms_m_s']:5.3f} m/s (RMS at the controller)  eye "
                f"{e['eye_ms_median']:5.1f} ms/frame  real-time factor "
                f"{e.get('real_time_factor_warm', e['real_time_factor']):5.3f}"
            )
        ratios = ", ".join(f"{c} {r:.2f}" for c, r in camera["camera_over_truth_peak"].items())
        print(f"peak force camera / ground truth: {ratios}")
    print("targets:", m["targets"])
    if "timing_s" in m:
        print(timing_line(m["timing_s"]))


def save_trajectories(folder, logs_by_condition: dict, dt: float) -> None:
    """One ``trajectory_<condition>.npz`` per condition: t, x_e, x_o (as the controller used it),
    x_o_true (simulator), f_int, k_o, b_o, m_o (+ more),
    arrays with a leading seed axis (then swing and sample axes for swing-structured runs).
    """
    for condition, logs in logs_by_condition.items():
        steps = logs["x_e"].shape[-2]
        write_npz(
            folder / f"trajectory_{condition}.npz",
            t=np.arange(steps) * dt,
            x_e=logs["x_e"],
            xd_e=logs["xd_e"],
            x_o=logs["x_o"],
            xd_o=logs["xd_o"],
            x_o_true=logs["x_o_true"],
            xd_o_true=logs["xd_o_true"],
            f_int=logs["f_contact"][..., [0, 2]],
            f_o=logs["f_o"],
            k_o=logs["k_o"],
            b_o=logs["b_o"],
            m_o=logs["m_o"],
            margins=logs["margins"],
            inside=logs["inside"],
            learning=logs["learning"],
            in_contact=logs["in_contact"],
            object_seen=logs["object_seen"],
        )


def catching_figures(folder: Path, result: ExperimentResult) -> None:
    """``fig6_catching.png`` (Fig. 6 style), ``virtual_impedance.png``, ``peak_force_per_swing.png``."""
    logs, config = result.logs, result.config.task
    f_cd, radius, r_b = config.learner.f_desired, config.learner.radius, config.learner.r_b
    plt = _pyplot()
    dt = result.dt
    last = config.swings - 1
    t = np.arange(logs["learned"]["x_e"].shape[-2]) * dt
    fig, ax = plt.subplots(2, 2, figsize=(11, 7))
    lg = logs["learned"]
    inside = lg["inside"][0, last]
    t_c = t[np.argmax(inside)] if inside.any() else None
    a = ax[0, 0]
    a.plot(t, lg["x_e"][0, last, :, 0], "-", label="hand X_e (learned, last swing)")
    a.plot(t, lg["x_o"][0, last, :, 0], "--", label="object X_o")
    a.plot(t, logs["plain"]["x_e"][0, 0, :, 0], ":", label="hand X_e (plain)")
    if t_c is not None:
        a.axvline(t_c, color="k", lw=0.8, label="t_c")
    a.set(xlabel="t [s]", ylabel="x [m]", title="(a) positions along x")
    a.legend(fontsize=7)
    a = ax[0, 1]
    for c in ("plain", "frozen"):
        a.plot(t, force_norm(logs[c])[0, 0], label=c)
    a.set(xlabel="t [s]", ylabel="|F_int| [N]", title="(b) interaction force without learning")
    a.legend(fontsize=7)
    a = ax[1, 0]
    f = force_norm(lg)[0]
    a.plot(t, f[0], alpha=0.6, label="learned, swing 1")
    a.plot(t, f[last], label=f"learned, swing {last + 1}")
    a.axhline(f_cd, color="k", ls=":", lw=0.8, label="F_cd")
    a.set(xlabel="t [s]", ylabel="|F_int| [N]", title="(c) interaction force with learning")
    a.legend(fontsize=7)
    a = ax[1, 1]
    rho = np.linspace(0, radius, 200)
    a.plot(rho, np.asarray(gain_alpha(rho, radius, r_b)))
    a.set(xlabel="|X_r| [m]", ylabel="alpha", title="gain function (Eq. 62)")
    fig.tight_layout()
    save_figure(fig, folder / "fig6_catching.png")
    plt.close(fig)

    fig, ax = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for k, (key, unit) in enumerate((("k_o", "N/m"), ("b_o", "N s/m"), ("m_o", "kg"))):
        ax[k].plot(t, lg[key][0, 0, :, 0], alpha=0.6, label="swing 1")
        ax[k].plot(t, lg[key][0, last, :, 0], label=f"swing {last + 1}")
        ax[k].set_ylabel(f"{key} (x) [{unit}]")
    ax[0].legend(fontsize=7)
    ax[-1].set_xlabel("t [s]")
    fig.suptitle("virtual impedance along x (seed 0)")
    save_figure(fig, folder / "virtual_impedance.png")
    plt.close(fig)

    fig, a = plt.subplots(figsize=(6, 4))
    peaks = force_norm(lg).max(-1)  # (seeds, swings)
    a.errorbar(
        np.arange(1, config.swings + 1), peaks.mean(0), peaks.std(0), fmt="o-", label="learned"
    )
    for c in ("plain", "frozen"):
        a.axhline(
            force_norm(logs[c])[:, 0].max(-1).mean(),
            ls="--",
            label=c,
            color="C1" if c == "plain" else "C2",
        )
    a.set(xlabel="swing", ylabel="peak |F_int| [N]", title="peak force per swing (mean +- std)")
    a.legend()
    save_figure(fig, folder / "peak_force_per_swing.png")
    plt.close(fig)


def hitting_figures(folder: Path, result: ExperimentResult) -> None:
    """``fig7_hitting.png`` (Fig. 7 style, the continuous run) and ``gain_beta.png``."""
    logs = {c: lg["final"] for c, lg in result.logs.items()}
    config = result.config.task
    radius, r_b = config.learner.radius, config.learner.r_b
    plt = _pyplot()
    t = np.arange(logs["learned"]["x_e"].shape[-2]) * result.dt
    fig, ax = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for c, style in (("learned", "-"), ("plain", ":")):
        ax[0].plot(t, logs[c]["x_e"][0, 0, :, 0], style, label=f"hand X_e ({c})")
        ax[0].plot(
            t,
            logs[c]["x_o"][0, 0, :, 0],
            "--" if c == "learned" else "-.",
            alpha=0.7,
            label=f"object X_o ({c})",
        )
    ax[0].set(ylabel="x [m]", title="(a) positions along x (seed 0)")
    ax[0].legend(fontsize=7, ncol=2)
    ax[1].plot(t, force_norm(logs["learned"])[0, 0], label="learned")
    ax[1].plot(t, force_norm(logs["plain"])[0, 0], alpha=0.6, label="plain")
    ax[1].set(ylabel="|F_int| [N]", title="(b) interaction force")
    ax[1].legend(fontsize=7)
    ax[2].plot(t, logs["learned"]["k_o"][0, 0, :, 0], label="K_o (x) [N/m]")
    ax[2].plot(t, 10 * logs["learned"]["b_o"][0, 0, :, 0], label="10 B_o (x) [N s/m]")
    ax[2].set(xlabel="t [s]", title="virtual impedance (learned)")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, folder / "fig7_hitting.png")
    plt.close(fig)
    fig, a = plt.subplots(figsize=(5, 3.5))
    rho = np.linspace(0, radius, 400)
    a.plot(rho, np.asarray(gain_beta(rho, radius, r_b)))
    a.set(xlabel="|X_r| [m]", ylabel="beta", title="gain function (Eq. 66, jump at R_b as printed)")
    save_figure(fig, folder / "gain_beta.png")
    plt.close(fig)
