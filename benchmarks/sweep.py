"""Sweep throughput: closed-loop learning rollouts over 1, 2, 4, ... devices vs MuJoCo C.

    python benchmarks/sweep.py [--batch 4096] [--steps 500] [--float32] [--per-device] [--spmd]
        [--solver-iterations 4 8] [--solver cg] [--jacobian sparse] [--warp]
        [--kernel xla triton triton-inside]

One run prints a table: steps/s of the catching loop with online learning (``experiments/sweep.py``'s
vmapped function: MJX physics + impedance control + learner), its run axis split over the first
n devices for n = 1, 2, 4, ... up to all devices (each device runs its slice with its own
executable, called from its own thread: ``experiments.devices.OnDevices``, as in
``experiments/sweep.py``), against MuJoCo C's
``mujoco.rollout`` (physics only, zero torques, all host cores) on the same scene and batch, measured
in the same run. A third row, MJX physics alone (``mjx.step`` in a ``lax.scan``, zero torques, the
same solver settings and batch, one device), bounds what the learning loop can reach on that
device: the loop adds the controller, the learner and the per-run models of the sweep on top of it.
``--batch`` is the whole batch (strong scaling: n devices share it); with ``--per-device`` every
device gets ``--batch`` runs (weak scaling: n devices run n times the batch, as a sweep larger than
one device's memory does). The gradient-cost rows time, in the same run, the exact gradient of the
catching loop with respect to all network weights (implicit derivative of the constraint solve,
per-step rematerialisation, the scene's solver settings: ``benchmarks/gradients.py``'s ``catching``
case) against its forward rollout, on ``--grad-batch`` conditions that reach the hand over
``--grad-steps`` samples (1 s by default; ``--grad-batch 0`` skips them). With ``--warp`` the
physics-alone row is repeated on MuJoCo Warp (``mjx.put_model(m, impl="warp")``, the same scan;
needs ``pip install -e ".[warp]"``), with the largest difference of its results from MJX's: the
learning loop itself runs on MJX's JAX implementation only (its staged calls have no Warp version).
``--solver`` / ``--jacobian`` set MuJoCo's ``opt.solver`` / ``opt.jacobian`` on every row (MJX and C
alike, ``hec_jax.mjx_scene.set_solver_options``); when they differ from scene.xml's, MuJoCo C is
timed with scene.xml's as well and the ratios use the faster C row, so that a setting that suits MJX
cannot make the baseline look slower. ``--kernel xla triton`` times the loop with each
implementation of the learner's network step (``hec_jax.nets.network_step``; "triton" is a Pallas
Triton kernel on CUDA GPUs and the XLA reference elsewhere) and prints how far their runs' peak
contact forces differ, and the share of run-steps in which the learner updated its weights (the
kernel writes only those runs' weights). A "-inside" variant (``triton-inside``, ``xla-inside``)
evaluates the networks only inside the virtual sphere (``LearnerConfig(nets_outside=False)``:
outside it Eq. 47 gives F_o = 0, so forces and learning are the same; the kernel then reads no
weights of runs outside the sphere); the share of run-steps inside the sphere is printed too.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

if "--float32" not in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402
from mujoco import rollout as mj_rollout  # noqa: E402

from benchmarks.gradients import _compiled, _timed, catching_case  # noqa: E402
from experiments import task_loop as tl  # noqa: E402
from experiments.devices import OnDevices, Sharded  # noqa: E402
from hec_jax.mjx_scene import (  # noqa: E402
    PendulumConditions,
    default_conditions,
    load_mj_model,
    set_solver_options,
)
from hec_jax.nets import LearnerConfig  # noqa: E402

# network-step variants: kernel, and "-inside" for LearnerConfig(nets_outside=False)
VARIANTS = ("xla", "triton", "xla-inside", "triton-inside")


def learner_variant(learner: LearnerConfig, variant: str) -> LearnerConfig:
    kernel, _, where = variant.partition("-")
    return replace(learner, kernel=kernel, nets_outside=where != "inside")


def best_of(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--float32", action="store_true")
    p.add_argument("--per-device", action="store_true", help="--batch runs on every device")
    p.add_argument(
        "--spmd",
        action="store_true",
        help="also time n > 1 devices as one GSPMD program (experiments.devices.Sharded; not "
        "for the Triton kernel on GPUs)",
    )
    p.add_argument("--solver-iterations", type=int, nargs=2, default=None, metavar=("IT", "LS"))
    p.add_argument("--solver", choices=("newton", "cg"), default=None, help="opt.solver")
    p.add_argument("--jacobian", choices=("dense", "sparse"), default=None, help="opt.jacobian")
    p.add_argument("--c-repeats", type=int, default=3, help="timed repeats of mujoco.rollout")
    p.add_argument("--grad-batch", type=int, default=16, help="0: no gradient-cost row")
    p.add_argument("--grad-steps", type=int, default=1000, help="gradient horizon [1 ms samples]")
    p.add_argument(
        "--warp",
        action="store_true",
        help="also time physics alone on MuJoCo Warp (MJX impl='warp', needs warp-lang)",
    )
    p.add_argument(
        "--kernel",
        nargs="+",
        choices=VARIANTS,
        default=["xla"],
        help="learner network step(s) to time (hec_jax.nets.network_step; triton: a Pallas "
        "Triton kernel on CUDA GPUs); '-inside': the networks evaluated only inside the virtual "
        "sphere (LearnerConfig.nets_outside=False: the same forces and learning)",
    )
    args = p.parse_args(argv)
    if args.warp and importlib.util.find_spec("warp") is None:  # fail before the long rows
        p.error('--warp needs warp-lang: pip install -e ".[warp]"')
    B, T = args.batch, args.steps
    config = tl.TaskConfig(
        learner=LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3),
        swing_steps=T,
        swings=1,
        solver_iterations=None if args.solver_iterations is None else args.solver_iterations[0],
        ls_iterations=None if args.solver_iterations is None else args.solver_iterations[1],
        solver=args.solver,
        jacobian=args.jacobian,
    )
    base = default_conditions()
    sw = tl.switches("learned")

    def batch_of(size):
        release = jnp.linspace(-0.55, -0.45, size)  # distinct runs: vmap cannot hoist the work
        conditions = PendulumConditions(
            **{k: jnp.broadcast_to(v, (size,)) for k, v in base._asdict().items()}
        )._replace(release_angle=release)
        return jax.random.split(jax.random.PRNGKey(0), size), conditions, release

    rows = []

    def add_row(row):
        """Keeps a table row and prints it at once (progress of a long run)."""
        rows.append(row)
        print(" | ".join(row), flush=True)

    n_dev = jax.device_count()
    counts = [n for n in (1, 2, 4, 8, 16) if n <= n_dev and (args.per_device or B % n == 0)]
    rates = {}  # (kernel, devices) -> steps/s
    peaks = {}  # kernel -> each run's peak contact force on 1 device [N]
    learning_fraction = inside_fraction = None
    for kernel in args.kernel:
        sweep = tl.make_sweep(replace(config, learner=learner_variant(config.learner, kernel)))

        def per_run(k, c, sweep=sweep):
            """Each run's peak contact force [N] and shares of steps learning / inside."""
            logs = sweep(k, sw, c)
            f = jnp.abs(logs["f_contact"])
            peak = jnp.max(f, axis=tuple(range(1, f.ndim)))
            flat = lambda x: x.reshape(x.shape[0], -1).astype(peak.dtype)  # noqa: E731
            return peak, flat(logs["learning"]).mean(1), flat(logs["inside"]).mean(1)

        triton_gpu = kernel.startswith("triton") and jax.default_backend() == "gpu"
        ways = [(n, OnDevices) for n in counts]
        if args.spmd and not triton_gpu:  # GSPMD cannot split the Triton kernel
            ways += [(n, Sharded) for n in counts if n > 1]
        for n, strategy in ways:
            # OnDevices: every device runs its slice of the runs with its own executable, called
            # from its own thread (as experiments/sweep.py); Sharded: one GSPMD program
            fn = strategy(per_run, jax.devices()[:n], (0, 0))
            size = B * n if args.per_device else B
            keys, conditions, _ = batch_of(size)
            placed = fn.place(keys, conditions)
            t0 = time.perf_counter()
            peak, learning, inside = fn.run(placed)
            compile_s = time.perf_counter() - t0
            if n == counts[0]:
                peaks[kernel] = peak
                learning_fraction, inside_fraction = float(learning.mean()), float(inside.mean())
            wall = best_of(lambda fn=fn, placed=placed: fn.run(placed))
            same = ""
            if n > counts[0] and not args.per_device:  # the same runs as on one device
                diff = float(np.max(np.abs(peak - peaks[kernel])))
                same = f"; peaks differ from 1 device's by at most {diff:.2g} N"
            if strategy is Sharded:
                add_row(
                    (
                        f"  the same as one GSPMD program (--spmd), {n} device(s), batch {size}",
                        f"{size * T / wall:.3g}",
                        f"compile {compile_s:.0f} s, best of 3: {wall:.2f} s, "
                        f"{size * T / wall / rates[kernel, counts[0]]:.2f}x 1 device{same}",
                    )
                )
                continue
            rates[kernel, n] = size * T / wall
            add_row(
                (
                    f"MJX learning loop ({kernel} network step), {n} device(s), batch {size}",
                    f"{rates[kernel, n]:.3g}",
                    f"compile {compile_s:.0f} s, best of 3: {wall:.2f} s{same}",
                )
            )
    first = args.kernel[0]

    _, _, release = batch_of(B)

    m = set_solver_options(  # the same solver settings as the MJX loop
        load_mj_model(),
        config.solver_iterations,
        config.ls_iterations,
        config.solver,
        config.jacobian,
    )
    hinge_adr = int(m.jnt_qposadr[m.joint("hinge").id])

    def physics_row(impl):
        """Times ``mjx.step`` in a scan (zero torques) with MJX's ``impl``; returns the rate, the
        row and each run's largest hinge angle and final qpos (to compare implementations)."""
        mx = mjx.put_model(m, impl=impl)
        if impl == "warp":  # contact buffers are shared by all worlds: one hand-cube contact each
            d0 = mjx.make_data(m, impl="warp", naconmax=max(B, 8), njmax=16)
        else:
            d0 = mjx.make_data(mx)

        @jax.jit
        def physics_only(release):
            def one(angle):
                def step(d, _):
                    d = mjx.step(mx, d)
                    return d, d.qpos[hinge_adr]

                d = d0.replace(qpos=d0.qpos.at[hinge_adr].set(angle))
                d, hinge = jax.lax.scan(step, d, None, length=T)
                return jnp.max(hinge), d.qpos

            return jax.vmap(one)(release)

        t0 = time.perf_counter()
        result = [np.asarray(x) for x in jax.block_until_ready(physics_only(release))]
        compile_s = time.perf_counter() - t0
        wall = best_of(lambda: jax.block_until_ready(physics_only(release)))
        rate = B * T / wall
        what = "MJX physics only (mjx.step scan)" if impl == "jax" else "MuJoCo Warp physics only"
        row = (
            f"{what}, 1 device, batch {B}",
            f"{rate:.3g}",
            f"compile {compile_s:.0f} s, best of 3: {wall:.2f} s",
        )
        return rate, row, result

    phys_rate, row, jax_result = physics_row("jax")
    add_row(row)
    warp_rate = None
    if args.warp:
        warp_rate, row, warp_result = physics_row("warp")
        hinge_diff, qpos_diff = (
            float(np.max(np.abs(w - j))) for w, j in zip(warp_result, jax_result, strict=True)
        )
        add_row(
            (
                row[0],
                row[1],
                f"{row[2]}; vs MJX: largest hinge angle {hinge_diff:.1e} rad, final qpos "
                f"{qpos_diff:.1e} rad",
            )
        )

    def c_row(m_c, what):
        """Times MuJoCo C's ``mujoco.rollout`` (zero torques, all host cores) on ``m_c``."""
        d = mujoco.MjData(m_c)
        nstate = mujoco.mj_stateSize(m_c, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        states = np.zeros((B, nstate))
        for i, angle in enumerate(np.asarray(release)):
            mujoco.mj_resetData(m_c, d)
            d.qpos[hinge_adr] = angle
            mujoco.mj_getState(m_c, d, states[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
        ctrl = np.zeros((B, T, m_c.nu))
        threads = os.cpu_count() or 1
        datas = [mujoco.MjData(m_c) for _ in range(threads)]
        with mj_rollout.Rollout(nthread=threads) as r:
            r.rollout([m_c] * B, datas, states, ctrl)
            wall = best_of(lambda: r.rollout([m_c] * B, datas, states, ctrl), args.c_repeats)
        add_row(
            (
                f"MuJoCo C mujoco.rollout, physics only, {threads} threads, batch {B}",
                f"{B * T / wall:.3g}",
                f"{what}, best of {args.c_repeats}: {wall:.2f} s",
            )
        )
        return B * T / wall

    def solver_name(m_c):
        return (
            f"{mujoco.mjtSolver(m_c.opt.solver).name}, {mujoco.mjtJacobian(m_c.opt.jacobian).name}"
        )

    def effective_settings(m_c):
        """(solver, jacobian) as MuJoCo runs them: ``auto`` is dense below 60 dofs."""
        jacobian = m_c.opt.jacobian
        if jacobian == mujoco.mjtJacobian.mjJAC_AUTO:
            sparse = m_c.nv >= 60
            jacobian = mujoco.mjtJacobian.mjJAC_SPARSE if sparse else mujoco.mjtJacobian.mjJAC_DENSE
        return m_c.opt.solver, jacobian

    c_rates = [c_row(m, f"same settings ({solver_name(m)})")]
    m_scene = set_solver_options(load_mj_model(), config.solver_iterations, config.ls_iterations)
    if effective_settings(m_scene) != effective_settings(m):
        c_rates.append(c_row(m_scene, f"scene.xml's {solver_name(m_scene)}"))
    c_rate = max(c_rates)  # the baseline: MuJoCo C at its fastest of the settings timed

    grad_ratio = None
    if args.grad_batch > 0:
        forward, grads, fargs = catching_case(
            args.grad_steps, args.grad_batch, jnp.float32 if args.float32 else jnp.float64
        )
        fns = {"forward": forward, "gradient": grads["implicit+remat"]}
        grad_compile_s = {}
        for name, fn in fns.items():
            out, grad_compile_s[name] = _compiled(fn, *fargs)
            if not all(bool(np.all(np.isfinite(x))) for x in jax.tree_util.tree_leaves(out)):
                raise FloatingPointError(f"non-finite {name} in the gradient-cost row")
        times = {name: np.inf for name in fns}
        for _ in range(3):  # interleaved, so that load changes hit both alike
            for name, fn in fns.items():
                times[name] = min(times[name], _timed(fn, *fargs, repeat=1))
        grad_ratio = times["gradient"] / times["forward"]
        for name, what in (
            ("forward", "catching loop forward (rollout), scene.xml's solver"),
            ("gradient", "value_and_grad, all weights (implicit+remat), scene.xml's"),
        ):
            add_row(
                (
                    f"{what}, batch {args.grad_batch} x {args.grad_steps} steps",
                    f"{args.grad_batch * args.grad_steps / times[name]:.3g}",
                    f"compile {grad_compile_s[name]:.0f} s, best of 3: {times[name]:.2f} s",
                )
            )

    dtype = "float32" if args.float32 else "float64"
    print(
        f"\n{jax.devices()[0].device_kind} x {n_dev} ({jax.default_backend()}), {dtype}, "
        f"batch {B}{' per device' if args.per_device else ''}, {T} steps per run, solver "
        f"iterations {m.opt.iterations} / line search {m.opt.ls_iterations}, {solver_name(m)}\n"
    )
    print(f"{'what':62s} {'steps/s':>10s}  notes")
    for what, rate, note in rows:
        print(f"{what:62s} {rate:>10s}  {note}")
    print("\nratios (against the fastest MuJoCo C row):")
    print(
        f"  MJX physics only / mujoco.rollout = {phys_rate / c_rate:.2f} (the bound for the "
        f"learning loop on one device); learning loop on 1 device / MJX physics only = "
        f"{rates[first, counts[0]] / phys_rate:.2f}"
    )
    print(
        f"  the learner updated its weights in {100 * learning_fraction:.1f}% of the run-steps "
        f"(the catching task learns only while the cube is inside the virtual sphere, "
        f"{100 * inside_fraction:.1f}% of the run-steps)"
    )
    for kernel in args.kernel[1:]:
        diff = np.abs(peaks[kernel] - peaks[first])
        print(
            f"  {kernel} / {first} network step: {rates[kernel, counts[0]] / rates[first, counts[0]]:.2f}"
            f" (1 device); peak contact force per run differs by at most {diff.max():.3g} N "
            f"(median {np.median(diff):.2g} N, largest peak {peaks[first].max():.3g} N)"
        )
    if warp_rate is not None:
        print(
            f"  MuJoCo Warp physics only / mujoco.rollout = {warp_rate / c_rate:.2f}; "
            f"/ MJX physics only = {warp_rate / phys_rate:.2f}"
        )
    if grad_ratio is not None:
        print(f"  exact gradient / forward rollout (catching, 1 device) = {grad_ratio:.2f}")
    for kernel in args.kernel:
        for n in counts:
            if (kernel, n) not in rates:
                continue
            print(
                f"  {n} device(s), {kernel} network step: learning loop / mujoco.rollout = "
                f"{rates[kernel, n] / c_rate:.2f}, speed-up over 1 device = "
                f"{rates[kernel, n] / rates[kernel, counts[0]]:.2f}"
            )


if __name__ == "__main__":
    main()
