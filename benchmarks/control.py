"""Control-step latency and closed-loop throughput: MJX (vmapped) vs MuJoCo C, on CPU.

    python benchmarks/control.py [--steps 200] [--batches 1 64 1024]

Rows (steps/s = simulated control steps of one environment per wall-clock second, summed over the
batch; compile time reported apart):
* jitted control step: ``apply`` of the impedance controller on a TaskObs (latency per call);
* MJX closed loop: ``rollout`` (physics + observe + controller in one lax.scan), vmapped over B;
* C closed loop, Python loop: ``rollout_c`` with the same jitted ``apply`` on MuJoCo C quantities;
* C open loop, ``mujoco.rollout``: physics only, replaying the torques of the MJX run (no
  controller in the loop; an upper bound for C physics throughput, multi-threaded over the batch).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax  # noqa: E402

if "--float32" not in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import rollout as mj_rollout  # noqa: E402

from hec_jax import control as C  # noqa: E402
from hec_jax import mjx_scene as S  # noqa: E402


def _time(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--float32", action="store_true", help="MJX in float32 (default float64)")
    args = ap.parse_args(argv)
    T = args.steps

    mm = S.load_mj_model()
    ids = S.scene_ids(mm)
    mx = S.load_mjx_model(mm)
    q_home = S.solve_posture(mm, ids, S.X_HOME)
    cond = S.default_conditions()
    params = C.impedance_params(1.0, 40.0, 400.0)
    vp = C.virtual_params(0.0, 20.0, 400.0, 0.25)
    rows = []

    # 1. latency of one jitted control step (TaskObs from MuJoCo C at home)
    d = S.make_data_c(mm, ids, cond, q_home)
    cq = S.c_quantities(mm, d, ids)
    obs = C.observe_c(ids, d.qpos, d.qvel, cq, np.zeros(3))
    init, apply = C.make_impedance_controller()
    apply_j = jax.jit(apply)
    st = init(obs)
    tgt = C.Target(obs.x_e, jnp.zeros(2), jnp.zeros(2))
    jax.block_until_ready(apply_j(params, vp, tgt, st, obs))
    n = 2000
    dt_call = _time(
        lambda: [jax.block_until_ready(apply_j(params, vp, tgt, st, obs)) for _ in range(n)]
    )
    lat_us = dt_call / n * 1e6
    rows.append(("jitted control step (apply), latency", 1, f"{lat_us:.1f} us/call", ""))

    # 2. MJX closed-loop rollout throughput, vmapped
    pinit, policy = C.make_mjx_policy(ids)

    def run_one(release):
        c = cond._replace(release_angle=release)
        d0 = S.make_data(mx, ids, c, jnp.asarray(q_home))
        x_d = d0.site_xpos[ids.hand_site][jnp.array(S.TASK_AXES)]
        ps0 = pinit(mx, d0, params, vp, C.Target(x_d, jnp.zeros(2), jnp.zeros(2)))
        return S.rollout(mx, ids, d0, policy, ps0, jnp.zeros((T, 3)), c)[1]

    mjx_sps = {}
    ctrl_replay = None
    for B in args.batches:
        rel = jnp.linspace(-0.6, -0.45, B)
        t0 = time.perf_counter()
        f = jax.jit(jax.vmap(run_one)).lower(rel).compile()
        t_c = time.perf_counter() - t0
        out = jax.block_until_ready(f(rel))
        wall = _time(lambda f=f, rel=rel: jax.block_until_ready(f(rel)))
        mjx_sps[B] = B * T / wall
        rows.append(
            ("MJX closed loop (vmap)", B, f"{mjx_sps[B]:.3g} steps/s", f"compile {t_c:.1f} s")
        )
        if ctrl_replay is None:
            ctrl_replay = np.asarray(out.ctrl[0])

    # 3. MuJoCo C closed loop, Python loop with the same jitted controller
    cpinit, cpolicy = C.make_c_policy(ids)

    def c_loop():
        d = S.make_data_c(mm, ids, cond, q_home)
        cq = S.c_quantities(mm, d, ids)
        ps0 = cpinit(
            d, cq, params, vp, C.Target(jnp.asarray(cq.x_hand[[0, 2]]), jnp.zeros(2), jnp.zeros(2))
        )
        S.rollout_c(mm, ids, d, cpolicy, ps0, np.zeros((T, 3)), cond)

    c_loop()
    c_sps = T / _time(c_loop, repeat=2)
    rows.append(("C closed loop (Python loop + jitted apply)", 1, f"{c_sps:.3g} steps/s", ""))

    # 4. mujoco.rollout, open loop (torque replay), batches
    roll_sps = {}
    for B in args.batches:
        d = S.make_data_c(mm, ids, cond, q_home)
        nstate = mujoco.mj_stateSize(mm, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        s0 = np.zeros(nstate)
        mujoco.mj_getState(mm, d, s0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        init_state = np.tile(s0, (B, 1))
        ctrl = np.tile(ctrl_replay[None], (B, 1, 1))
        datas = [mujoco.MjData(mm) for _ in range(min(B, os.cpu_count() or 1))]
        with mj_rollout.Rollout(nthread=len(datas)) as r:
            r.rollout([mm] * B, datas, init_state, ctrl)
            wall = _time(
                lambda r=r, init_state=init_state, ctrl=ctrl, B=B, datas=datas: r.rollout(
                    [mm] * B, datas, init_state, ctrl
                )
            )
        roll_sps[B] = B * T / wall
        rows.append(
            (
                "C open loop (mujoco.rollout, torque replay)",
                B,
                f"{roll_sps[B]:.3g} steps/s",
                f"{len(datas)} threads",
            )
        )

    dtype = "float32" if args.float32 else "float64"
    print(
        f"\nJAX device: {jax.devices()[0].device_kind} ({jax.default_backend()}), MJX {dtype}; "
        f"MuJoCo C on {os.cpu_count()} CPU cores; {T} steps per rollout (dt = 1 ms)\n"
    )
    print(f"{'what':46s} {'batch':>6s} {'result':>18s}  notes")
    for what, b, res, note in rows:
        print(f"{what:46s} {b:6d} {res:>18s}  {note}")
    print("\nratios (MJX closed loop / C):")
    for B in args.batches:
        print(
            f"  B={B:5d}: MJX/C-python-loop = {mjx_sps[B] / c_sps:7.2f}, "
            f"MJX/mujoco.rollout = {mjx_sps[B] / roll_sps[B]:7.3f}"
        )


if __name__ == "__main__":
    main()
