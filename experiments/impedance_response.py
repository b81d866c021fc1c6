"""Step force on the hand (no object): simulated response against the target impedance (Eq. 40).

    python experiments/impedance_response.py --out runs/impedance_response --seed 0

The force is applied on the hand body (``xfrc_applied``) and the controller uses exactly that force
as F_int. The run folder holds ``config.json`` (m_e, b_e, k_e diagonals, seed, versions, device),
``trajectory.npz`` (t, x_e, xd_e, x_d, f_ext, f_int, x_target) and ``response.png``. The reference
``x_target`` is the exact solution of Eq. 40 under the simulator's zero-order hold (matrix
exponential), computed here independently of the controller.
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
from scipy.linalg import expm  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from hec_jax import control as C  # noqa: E402
from hec_jax import mjx_scene as S  # noqa: E402


def zoh_reference(m, b, k, f, dt):
    A = np.array([[0.0, 1.0], [-k / m, -b / m]])
    E = expm(np.block([[A, np.array([[0.0], [1.0 / m]])], [np.zeros((1, 3))]]) * dt)
    x = np.zeros(2)
    out = np.empty((len(f), 2))
    for i, fk in enumerate(f):
        out[i] = x
        x = E[:2, :2] @ x + E[:2, 2] * fk
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", required=True, help="run folder")
    ap.add_argument("--seed", type=int, default=0, help="seed (draws the step force direction)")
    ap.add_argument("--m-e", type=float, nargs=2, default=[1.0, 1.0], help="[kg] M_e diagonal")
    ap.add_argument("--b-e", type=float, nargs=2, default=[40.0, 40.0], help="[N s/m] B_e diagonal")
    ap.add_argument("--k-e", type=float, nargs=2, default=[400.0, 400.0], help="[N/m] K_e diagonal")
    ap.add_argument("--force", type=float, default=10.0, help="[N] step magnitude")
    ap.add_argument("--t-step", type=float, default=0.1, help="[s] time of the step")
    ap.add_argument("--duration", type=float, default=1.5, help="[s]")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    angle = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(angle), np.sin(angle)])  # in the task plane (x, z)
    mm = S.load_mj_model()
    ids = S.scene_ids(mm)
    mx = S.load_mjx_model(mm)
    dt = float(mm.opt.timestep)
    n = int(round(args.duration / dt))
    t = np.arange(n) * dt
    f_ext = np.zeros((n, 3))
    on = t >= args.t_step
    f_ext[on, 0] = args.force * direction[0]
    f_ext[on, 2] = args.force * direction[1]

    params = C.impedance_params(args.m_e, args.b_e, args.k_e)
    vparams = C.virtual_params(0.0, 0.0, 0.0, 0.25)  # F_o = 0: plain impedance control
    cond = S.default_conditions(release_angle=0.0)  # pendulum at rest, 0.3 m away
    q_home = S.solve_posture(mm, ids, S.X_HOME)
    pinit, policy = C.make_mjx_policy(ids)

    @jax.jit
    def run(params, f_ext):
        d0 = S.make_data(mx, ids, cond, jnp.asarray(q_home))
        x_d = d0.site_xpos[ids.hand_site][jnp.array(S.TASK_AXES)]
        ps0 = pinit(mx, d0, params, vparams, C.Target(x_d, jnp.zeros(2), jnp.zeros(2)))
        return S.rollout(mx, ids, d0, policy, ps0, f_ext, cond)[1], x_d

    t0 = time.perf_counter()
    compiled = run.lower(params, jnp.asarray(f_ext)).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj, x_d = jax.block_until_ready(compiled(params, jnp.asarray(f_ext)))
    t_run = time.perf_counter() - t0
    print(f"compile {t_compile:.1f} s, run {t_run:.3f} s ({n} steps)")

    x_e = np.asarray(traj.aux["x_e"])
    xd_e = np.asarray(traj.aux["xd_e"])
    x_d = np.asarray(x_d)
    f_task = f_ext[:, list(S.TASK_AXES)]
    ref = np.stack(
        [
            zoh_reference(args.m_e[a], args.b_e[a], args.k_e[a], f_task[:, a], dt)[:, 0]
            for a in range(2)
        ],
        axis=1,
    )
    dx = x_e - x_d[None, :]
    rel_rms = np.sqrt(np.mean((dx - ref) ** 2, axis=0)) / np.sqrt(np.mean(ref**2, axis=0))
    print("relative RMS error per axis (x, z):", rel_rms)

    out = Path(args.out)
    _common.write_config(
        out,
        args.seed,
        dict(
            experiment="impedance_response",
            m_e=list(args.m_e),
            b_e=list(args.b_e),
            k_e=list(args.k_e),
            force=args.force,
            force_direction_xz=direction.tolist(),
            t_step=args.t_step,
            duration=args.duration,
            dt=dt,
            task_axes="(x, z) of the world frame",
            relative_rms_error_xz=rel_rms.tolist(),
            saturated=bool(np.asarray(traj.aux["saturated"]).any()),
            compile_s=t_compile,
            run_s=t_run,
        ),
    )
    _common.save_npz(
        out / "trajectory.npz",
        t=t,
        x_e=x_e,
        xd_e=xd_e,
        x_d=x_d,
        f_ext=f_task,
        f_int=np.asarray(traj.f_int)[:, list(S.TASK_AXES)],
        x_target=ref + x_d[None, :],
        tau=np.asarray(traj.ctrl),
    )
    fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    for a, name in enumerate("xz"):
        axes[a].plot(t, dx[:, a] * 1e3, label="simulated (MJX)")
        axes[a].plot(t, ref[:, a] * 1e3, "--", label="target impedance (Eq. 40)")
        axes[a].set_ylabel(f"d{name} [mm]")
        axes[a].legend(loc="lower right")
    axes[2].plot(t, f_task[:, 0], label="F_x")
    axes[2].plot(t, f_task[:, 1], label="F_z")
    axes[2].set_ylabel("F_ext [N]")
    axes[2].set_xlabel("t [s]")
    axes[2].legend()
    fig.suptitle(f"M_e={args.m_e}, B_e={args.b_e}, K_e={args.k_e}; rel. RMS err {rel_rms.round(4)}")
    _common.save_figure(fig, out / "response.png")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
