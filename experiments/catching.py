"""Catching (Sec. 6.2, Eqs. 59-62, Fig. 6): the hand learns to meet the swinging cube softly.

    python experiments/catching.py --out runs/catching --seed 0

The cube is released from the same angle every swing; the hand waits at X_d with the target
impedance of paper-notes Sec. 4. Conditions: ``plain`` (F_o = 0), ``frozen`` (the initial
networks, no learning) and ``learned`` (online learning over successive swings, weights carried
over; metrics on the last swing). ``--seeds`` network initialisations (vmapped). Writes
``config.json``, ``metrics.json``, ``trajectory_<condition>.npz`` and figures in the style of Fig. 6.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from experiments import task_loop as tl  # noqa: E402
from hec_jax.mjx_scene import default_conditions  # noqa: E402
from hec_jax.nets import gain_alpha  # noqa: E402
from hec_jax.runs import save_figure, start_run, write_json  # noqa: E402


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    tl.add_common_args(p, "runs/catching")
    p.add_argument("--swings", type=int, default=10)
    p.add_argument("--swing-s", type=float, default=2.0, help="duration of one swing [s]")
    p.add_argument("--mu", type=float, default=1e-3, help="weight of E_cf (Eq. 59)")
    p.add_argument("--f-cd", type=float, default=1.0, help="desired contact force F_cd [N]")
    return p.parse_args(argv)


def swing_metrics(logs, s: int, w: int, config: tl.TaskConfig) -> dict:
    """Metrics of seed ``s``, swing ``w``."""
    f = tl.force_norm(logs)[s, w]
    dt = config.controller.dt
    events = tl.contact_events(f, config.contact_threshold, min_gap=20)
    inside = logs["inside"][s, w]
    t_c = int(np.argmax(inside)) if inside.any() else -1
    out = {"peak_force": float(f.max()), "t_c": t_c * dt if t_c >= 0 else None}
    if events:
        i = max(events[0][0] - 1, 0)
        xd_o, xd_e = logs["xd_o"][s, w, i], logs["xd_e"][s, w, i]
        speed_o = float(np.linalg.norm(xd_o))
        out.update(
            t_contact=events[0][0] * dt,
            relative_speed_at_contact=float(np.linalg.norm(xd_o - xd_e)),
            object_speed_at_contact=speed_o,
            # 0: the hand waits, 1: it moves with the object at contact
            hand_follow_ratio=float(np.dot(xd_e, xd_o) / max(speed_o**2, 1e-12)),
            contacts=len(events),
        )
    else:
        out.update(contacts=0)
    tail = int(round(0.3 / dt))
    out["settle_force"] = float(f[-tail:].mean())
    return out


def main(argv=None):
    args = parse(argv)
    learner = tl.learner_from_args(args, "catching", args.f_cd)
    config = tl.config_from_args(args, learner, args.swing_s, args.swings)
    pendulum = default_conditions(release_angle=args.release_angle)
    settings = tl.run_settings(args, "catching", pendulum, learner, config)
    folder = start_run(args.out, args.seed, settings)
    t0 = time.perf_counter()
    logs, timing = tl.run_conditions(config, pendulum, args.seed, args.seeds)
    wall = time.perf_counter() - t0
    tl.save_trajectories(folder, logs, config.controller.dt)

    metrics = {"timing_s": {"total": wall, **timing}}
    last = args.swings - 1
    for condition, lg in logs.items():
        w = last if condition == "learned" else 0
        per_seed = [swing_metrics(lg, s, w, config) for s in range(args.seeds)]
        m = {
            key: tl.mean_std([p[key] for p in per_seed])
            for key in per_seed[0]
            if all(p.get(key) is not None for p in per_seed) and key in per_seed[-1]
        }
        m["swing_used"] = w
        m["stability"] = tl.stability_summary(lg)
        if condition == "learned":
            m["peak_force_per_swing"] = [
                tl.mean_std(
                    [swing_metrics(lg, s, k, config)["peak_force"] for s in range(args.seeds)]
                )
                for k in range(args.swings)
            ]
        metrics[condition] = m
    peak = {c: metrics[c]["peak_force"]["mean"] for c in tl.CONDITIONS}
    settle = metrics["learned"]["settle_force"]["mean"]
    metrics["targets"] = {
        "peak_learned_over_plain": peak["learned"] / peak["plain"],
        "peak_learned_over_frozen": peak["learned"] / peak["frozen"],
        "peak_at_most_half_of_both_baselines": bool(
            peak["learned"] <= 0.5 * min(peak["plain"], peak["frozen"])
        ),
        "settle_force_rel_error": abs(settle - args.f_cd) / args.f_cd,
        "settles_to_f_cd_within_20pct": bool(abs(settle - args.f_cd) <= 0.2 * args.f_cd),
        "learned_strictly_stable_every_sample": metrics["learned"]["stability"][
            "all_strictly_stable"
        ],
        "runtime_under_10_min": bool(wall < 600),
    }
    write_json(folder / "metrics.json", metrics)
    plot(folder, logs, config, args)
    print(f"run folder: {folder}")
    for c in tl.CONDITIONS:
        print(
            f"{c:8s} peak force {metrics[c]['peak_force']['mean']:7.1f} +- "
            f"{metrics[c]['peak_force']['std']:5.1f} N"
        )
    print("targets:", metrics["targets"])
    return metrics


def plot(folder, logs, config, args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dt = config.controller.dt
    last = args.swings - 1
    t = np.arange(config.swing_steps) * dt
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
        a.plot(t, tl.force_norm(logs[c])[0, 0], label=c)
    a.set(xlabel="t [s]", ylabel="|F_int| [N]", title="(b) interaction force without learning")
    a.legend(fontsize=7)
    a = ax[1, 0]
    f = tl.force_norm(lg)[0]
    a.plot(t, f[0], alpha=0.6, label="learned, swing 1")
    a.plot(t, f[last], label=f"learned, swing {last + 1}")
    a.axhline(args.f_cd, color="k", ls=":", lw=0.8, label="F_cd")
    a.set(xlabel="t [s]", ylabel="|F_int| [N]", title="(c) interaction force with learning")
    a.legend(fontsize=7)
    a = ax[1, 1]
    rho = np.linspace(0, args.radius, 200)
    a.plot(rho, np.asarray(gain_alpha(rho, args.radius, args.r_b)))
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
    peaks = tl.force_norm(lg).max(-1)  # (seeds, swings)
    a.errorbar(
        np.arange(1, args.swings + 1), peaks.mean(0), peaks.std(0), fmt="o-", label="learned"
    )
    for c in ("plain", "frozen"):
        a.axhline(
            tl.force_norm(logs[c])[:, 0].max(-1).mean(),
            ls="--",
            label=c,
            color="C1" if c == "plain" else "C2",
        )
    a.set(xlabel="swing", ylabel="peak |F_int| [N]", title="peak force per swing (mean +- std)")
    a.legend()
    save_figure(fig, folder / "peak_force_per_swing.png")
    plt.close(fig)


if __name__ == "__main__":
    main()
