"""The pendulum swings into the virtual sphere (Eqs. 45-48): the hand retreats before contact.

    python experiments/avoidance.py --out runs/avoidance --seed 0

Two runs in one vmapped rollout: non-contact impedance (K_o, B_o > 0) and plain impedance (F_o = 0).
The seed jitters the release angle (within paper-notes' 0.45-0.6 rad). Writes ``config.json``,
``trajectory.npz`` (t, x_e, xd_e, x_o, f_o, f_int, rho per run) and ``avoidance.png``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common  # noqa: E402

_common.enable_x64()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from hec_jax import control as C  # noqa: E402
from hec_jax import mjx_scene as S  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--k-o", type=float, default=400.0, help="[N/m] virtual stiffness")
    ap.add_argument("--b-o", type=float, default=20.0, help="[N s/m] virtual viscosity")
    ap.add_argument("--m-o", type=float, default=0.0, help="[kg] virtual inertia")
    ap.add_argument("--radius", type=float, default=0.25, help="[m] virtual sphere radius r")
    ap.add_argument("--duration", type=float, default=1.5, help="[s]")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    release = -float(rng.uniform(0.45, 0.6))
    mm = S.load_mj_model()
    ids = S.scene_ids(mm)
    mx = S.load_mjx_model(mm)
    dt = float(mm.opt.timestep)
    n = int(round(args.duration / dt))
    cond = S.default_conditions(release_angle=release)
    params = C.impedance_params(1.0, 40.0, 400.0)
    vp_on = C.virtual_params(args.m_o, args.b_o, args.k_o, args.radius)
    vp_on = C.project_stable(vp_on, params.m_e, params.b_e, params.k_e)  # Eq. 49
    vp_off = C.virtual_params(0.0, 0.0, 0.0, args.radius)
    q_home = S.solve_posture(mm, ids, S.X_HOME)
    pinit, policy = C.make_mjx_policy(ids)

    def run_one(vp):
        d0 = S.make_data(mx, ids, cond, jnp.asarray(q_home))
        x_d = d0.site_xpos[ids.hand_site][jnp.array(S.TASK_AXES)]
        ps0 = pinit(mx, d0, params, vp, C.Target(x_d, jnp.zeros(2), jnp.zeros(2)))
        return S.rollout(mx, ids, d0, policy, ps0, jnp.zeros((n, 3)), cond)[1]

    vps = jax.tree.map(lambda a, b: jnp.stack([a, b]), vp_on, vp_off)
    t0 = time.perf_counter()
    compiled = jax.jit(jax.vmap(run_one)).lower(vps).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj = jax.tree.map(np.asarray, jax.block_until_ready(compiled(vps)))
    t_run = time.perf_counter() - t0
    print(f"compile {t_compile:.1f} s, run {t_run:.3f} s (2 x {n} steps)")

    t = np.arange(n) * dt
    ax = list(S.TASK_AXES)
    summary = {}
    for i, name in enumerate(("virtual_sphere", "plain")):
        fc = np.linalg.norm(traj.f_contact[i], axis=1)
        hit = np.nonzero(fc > 0)[0]
        summary[name] = dict(
            first_contact_s=float(t[hit[0]]) if hit.size else None,
            peak_contact_force_N=float(fc.max()),
            max_hand_retreat_x_m=float((traj.aux["x_e"][i][:, 0] - traj.aux["x_e"][i][0, 0]).max()),
            min_distance_m=float(traj.aux["rho"][i].min()),
        )
    print(summary)
    out = Path(args.out)
    _common.write_config(
        out,
        args.seed,
        dict(
            experiment="avoidance",
            release_angle=release,
            conditions=cond._asdict(),
            m_e=params.m_e,
            b_e=params.b_e,
            k_e=params.k_e,
            m_o=vp_on.m_o,
            b_o=vp_on.b_o,
            k_o=vp_on.k_o,
            radius=args.radius,
            duration=args.duration,
            dt=dt,
            runs=["virtual_sphere", "plain (F_o = 0)"],
            summary=summary,
            compile_s=t_compile,
            run_s=t_run,
        ),
    )
    _common.save_npz(
        out / "trajectory.npz",
        t=t,
        x_e=traj.aux["x_e"],
        xd_e=traj.aux["xd_e"],
        x_o=traj.aux["x_o"],
        f_o=traj.aux["f_o"],
        f_int=traj.f_contact[:, :, ax],
        rho=traj.aux["rho"],
        run_names=np.array(["virtual_sphere", "plain"]),
    )
    fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    for i, (name, ls) in enumerate((("virtual sphere", "-"), ("F_o = 0", "--"))):
        axes[0].plot(t, traj.aux["x_e"][i][:, 0], ls, label=f"hand x ({name})")
        axes[1].plot(t, traj.aux["rho"][i], ls, label=f"|X_r| ({name})")
        axes[2].plot(t, np.linalg.norm(traj.f_contact[i], axis=1), ls, label=f"|F_int| ({name})")
    axes[0].plot(t, traj.aux["x_o"][1][:, 0], ":", label="cube x")
    axes[0].set_ylabel("x [m]")
    axes[1].axhline(args.radius, color="k", lw=0.5, label="r")
    axes[1].set_ylabel("distance [m]")
    axes[2].set_ylabel("contact force [N]")
    axes[2].set_xlabel("t [s]")
    for a in axes:
        a.legend(fontsize=8)
    _common.save_figure(fig, out / "avoidance.png")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
