"""Control-step latency and closed-loop throughput: MJX (vmapped) vs MuJoCo C, on CPU.

    python benchmarks/control.py [--steps 200] [--batches 1 64 1024]

Rows (steps/s = simulated control steps of one environment per wall-clock second, summed over the
batch; compile time reported apart):
* jitted control step: ``apply`` of the impedance controller on a TaskObs (latency per call);
* MJX closed loop: ``rollout`` (physics + observe + controller in one lax.scan), vmapped over B;
* C closed loop, Python loop: ``rollout_c`` with the same jitted ``apply`` on MuJoCo C quantities;
* C open loop, ``mujoco.rollout``: physics only, replaying the torques of the MJX run (no
  controller in the loop; an upper bound for C physics throughput, multi-threaded over the batch).

The controller holds the hand where it is at the release (target impedance ``--m-e --b-e --k-e``)
with a fixed virtual impedance (``--virtual``); the pendulum is the nominal one, its release angle
spread over [-0.6, -0.45] rad across the batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax import benchmarking as bench
from hec_jax.cli import command, parse, require
from hec_jax.control import ControllerConfig, impedance_params, virtual_params
from hec_jax.loop import TargetImpedance
from hec_jax.mjx_scene import (
    X_HOME,
    PendulumConfig,
    load_mj_model,
    load_mjx_model,
    make_data_c,
    scene_ids,
    solve_posture,
)
from hec_jax.report import timed


@dataclass(frozen=True)
class ControlBenchmark:
    """What the control benchmark runs: the hand's settings, rollout length and batches."""

    impedance: TargetImpedance = field(default_factory=TargetImpedance)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    pendulum: PendulumConfig = field(default_factory=PendulumConfig)
    # fixed virtual impedance: M_o [kg], B_o [N s/m], K_o [N/m], sphere radius r [m]
    virtual: tuple[float, float, float, float] = (0.0, 20.0, 400.0, 0.25)
    steps: int = 200  # control steps per rollout (the model's time step, 1 ms)
    batches: tuple[int, ...] = (1, 64, 1024)  # vmapped environments, one row each
    float32: bool = False  # MJX in float32 (default float64)

    def __post_init__(self):
        require(self, "count", "steps", "batches")
        require(self, "non_negative", "virtual")
        if not self.virtual[3] > 0:
            raise ValueError(f"--virtual: the sphere radius must be > 0, got {self.virtual[3]}")


@command
def main(argv=None):
    """Runs the benchmark on the flags in ``argv`` (None: the command line); prints its table."""
    cfg = parse(ControlBenchmark(), argv, __doc__)
    bench.float_dtype(cfg.float32)
    T = cfg.steps
    mm = load_mj_model()
    ids = scene_ids(mm)
    mx = load_mjx_model(mm)
    q_home = solve_posture(mm, ids, X_HOME)
    cond = cfg.pendulum.conditions()
    imp = cfg.impedance
    params = impedance_params(imp.m_e, imp.b_e, imp.k_e)
    vp = virtual_params(*cfg.virtual)
    rows = []

    # 1. latency of one jitted control step (TaskObs from MuJoCo C at the release)
    apply, (tgt, st, obs) = bench.control_step(mm, ids, cond, q_home, cfg.controller)
    jax.block_until_ready(apply(params, vp, tgt, st, obs))
    n = 2000
    t = bench.best_of(
        lambda: [jax.block_until_ready(apply(params, vp, tgt, st, obs)) for _ in range(n)]
    )
    rows.append(("jitted control step (apply), latency", 1, f"{t / n * 1e6:.1f} us/call", ""))

    # 2. MJX closed-loop rollout throughput, vmapped
    run_one = bench.control_rollout(mx, ids, q_home, cond, params, vp, T, cfg.controller)
    mjx_sps, ctrl_replay = {}, None
    for B in cfg.batches:
        rel = jnp.linspace(-0.6, -0.45, B)
        f, t_c = timed(lambda rel=rel: jax.jit(jax.vmap(run_one)).lower(rel).compile())
        out = jax.block_until_ready(f(rel))
        mjx_sps[B] = B * T / bench.best_of(lambda f=f, rel=rel: jax.block_until_ready(f(rel)))
        rows.append(
            ("MJX closed loop (vmap)", B, f"{mjx_sps[B]:.3g} steps/s", f"compile {t_c:.1f} s")
        )
        if ctrl_replay is None:
            ctrl_replay = np.asarray(out.ctrl[0])

    # 3. MuJoCo C closed loop, Python loop with the same jitted controller
    c_loop = bench.c_control_rollout(mm, ids, q_home, cond, params, vp, T, cfg.controller)
    c_loop()
    c_sps = T / bench.best_of(c_loop, repeat=2)
    rows.append(("C closed loop (Python loop + jitted apply)", 1, f"{c_sps:.3g} steps/s", ""))

    # 4. mujoco.rollout, open loop (torque replay), batches
    roll_sps = {}
    state = bench.full_state(mm, make_data_c(mm, ids, cond, q_home))
    for B in cfg.batches:
        threads = min(B, bench.host_threads())
        states, ctrl = np.tile(state, (B, 1)), np.tile(ctrl_replay[None], (B, 1, 1))
        roll_sps[B] = B * T / bench.c_rollout_seconds(mm, states, ctrl, threads)
        what = "C open loop (mujoco.rollout, torque replay)"
        rows.append((what, B, f"{roll_sps[B]:.3g} steps/s", f"{threads} threads"))

    dtype = "float32" if cfg.float32 else "float64"
    print(
        f"\nJAX device: {bench.device_name()}, MJX {dtype}; MuJoCo C on {bench.host_threads()} "
        f"CPU cores; {T} steps per rollout (dt = {ids.timestep * 1e3:g} ms)\n"
    )
    print("\n".join(bench.text_table(("what", "batch", "result", "notes"), (46, 6, 18), rows)))
    print("\nratios (MJX closed loop / C):")
    for B in cfg.batches:
        print(
            f"  B={B:5d}: MJX/C-python-loop = {mjx_sps[B] / c_sps:7.2f}, "
            f"MJX/mujoco.rollout = {mjx_sps[B] / roll_sps[B]:7.3f}"
        )


if __name__ == "__main__":
    main()
