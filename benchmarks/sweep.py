"""Sweep throughput: closed-loop learning rollouts over 1, 2, 4, ... devices vs MuJoCo C.

    python benchmarks/sweep.py [--batch 4096] [--steps 500] [--float32] [--per-device] [--spmd]
        [--solver-iterations 4 --ls-iterations 8] [--solver cg] [--jacobian sparse] [--warp]
        [--kernels xla triton triton-inside]

One run prints a table: steps/s of the catching loop with online learning (the sweep's task,
``hec_jax.loop.sweep_catching``, as ``experiments/sweep.py`` runs it: MJX physics + impedance
control + learner, one swing of ``--steps``, release angles spread over [-0.55, -0.45] rad), its
run axis split over the first n devices for n = 1, 2, 4, ... up to all devices (each device runs
its slice with its own executable, called from its own thread: ``hec_jax.loop.OnDevices``),
against MuJoCo C's ``mujoco.rollout`` (physics only, zero torques, all host cores) on the same
scene and batch, measured in the same run. A third row, MJX physics alone (``mjx.step`` in a
``lax.scan``, zero torques, the same solver settings and batch, one device), bounds what the
learning loop can reach on that device: the loop adds the controller, the learner and the per-run
models of the sweep on top of it. ``--batch`` is the whole batch (strong scaling: n devices share
it); with ``--per-device`` every device gets ``--batch`` runs (weak scaling). ``--spmd`` also
times n > 1 devices as one GSPMD program (``hec_jax.loop.Sharded``; not for the Triton kernel on
GPUs). The gradient-cost rows time, in the same run, the exact gradient of the catching loop with
respect to all network weights (implicit derivative of the constraint solve, per-step
rematerialisation, scene.xml's solver settings: ``benchmarks/gradients.py``'s ``catching`` case)
against its forward rollout, on ``--grad-batch`` conditions that reach the hand over
``--grad-steps`` samples (``--grad-batch 0`` skips them). With ``--warp`` the physics-alone row
is repeated on MuJoCo Warp (``mjx.put_model(m, impl="warp")``; needs ``pip install -e
".[warp]"``), with the largest difference of its results from MJX's. ``--solver`` /
``--jacobian`` / ``--solver-iterations`` / ``--ls-iterations`` set MuJoCo's options on every row
(MJX and C alike); when they differ from scene.xml's, MuJoCo C is timed with scene.xml's as well
and the ratios use the faster C row. ``--kernels xla triton`` times the loop with each
implementation of the learner's network step (``hec_jax.nets.network_step``; "triton" is a Pallas
Triton kernel on CUDA GPUs and the XLA reference elsewhere; default: the task's ``--kernel``) and
prints how far their runs' peak contact forces differ, and the share of run-steps in which the
learner updated its weights. A "-inside" variant (``triton-inside``, ``xla-inside``) evaluates the
networks only inside the virtual sphere (``--no-nets-outside``: outside it Eq. 47 gives F_o = 0,
so forces and learning are the same); the share of run-steps inside the sphere is printed too.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field

import jax
import numpy as np

from hec_jax import benchmarking as bench
from hec_jax.cli import command, parse, require
from hec_jax.loop import TaskConfig, sweep_catching
from hec_jax.mjx_scene import load_mj_model, set_solver_options


@dataclass(frozen=True)
class SweepBenchmark:
    """The sweep benchmark: the task (one swing of ``steps``), batch, devices and extra rows."""

    task: TaskConfig = field(default_factory=sweep_catching)
    batch: int = 256  # runs (the whole batch; per device with per_device)
    steps: int = 500  # control steps per run
    float32: bool = False  # float32 (default float64)
    per_device: bool = False  # batch runs on every device (weak scaling)
    spmd: bool = False  # also time n > 1 devices as one GSPMD program
    # network-step variants to time (their kernel and nets_outside replace the task's); empty:
    # the task's own (--kernel, --nets-outside)
    kernels: tuple[bench.Variant, ...] = ()
    c_repeats: int = 3  # timed repeats of mujoco.rollout
    grad_batch: int = 16  # conditions of the gradient-cost rows; 0: none
    grad_steps: int = 1000  # gradient horizon [1 ms samples]
    warp: bool = False  # also time physics alone on MuJoCo Warp (needs warp-lang)

    def __post_init__(self):
        require(self, "count", "batch", "steps", "c_repeats", "grad_steps")
        if not (isinstance(self.grad_batch, int) and self.grad_batch >= 0):
            raise ValueError(f"--grad-batch must be an integer >= 0, got {self.grad_batch}")


@command
def main(argv=None):
    """Runs the benchmark on the flags in ``argv`` (None: the command line); prints its table."""
    cfg = parse(SweepBenchmark(), argv, __doc__)
    if cfg.warp and importlib.util.find_spec("warp") is None:  # fail before the long rows
        raise SystemExit('--warp needs warp-lang: pip install -e ".[warp]"')
    dtype = bench.float_dtype(cfg.float32)
    B, T, task = cfg.batch, cfg.steps, bench.one_swing(cfg.task, cfg.steps)
    variants = cfg.kernels or (bench.variant_of(task.learner),)
    rows = []

    def add_row(*row):
        """Keeps a table row and prints it at once (progress of a long run)."""
        rows.append(row)
        print(" | ".join(row), flush=True)

    loop = bench.loop_rows(task, variants, B, T, cfg.per_device, cfg.spmd, add_row)
    _, _, release = bench.release_batch(task.pendulum.conditions(), B)
    it, ls = task.solver_iterations, task.ls_iterations
    m = set_solver_options(load_mj_model(), it, ls, task.solver, task.jacobian)
    phys = bench.physics_rows(m, release, T, cfg.warp, add_row)
    c_rate = bench.c_rows(
        m, set_solver_options(load_mj_model(), it, ls), release, T, cfg.c_repeats, add_row
    )
    grad_ratio = None
    if cfg.grad_batch > 0:
        grad_ratio = bench.gradient_rows(cfg.task, cfg.grad_batch, cfg.grad_steps, dtype, add_row)

    print(
        f"\n{jax.devices()[0].device_kind} x {jax.device_count()} ({jax.default_backend()}), "
        f"{'float32' if cfg.float32 else 'float64'}, batch {B}"
        f"{' per device' if cfg.per_device else ''}, {T} steps per run, solver iterations "
        f"{m.opt.iterations} / line search {m.opt.ls_iterations}, {bench.solver_name(m)}\n"
    )
    print("\n".join(bench.text_table(("what", "steps/s", "notes"), (62, 10), rows)))
    first, n1 = variants[0], loop.counts[0]
    one = loop.rates[first, n1]
    print("\nratios (against the fastest MuJoCo C row):")
    print(
        f"  MJX physics only / mujoco.rollout = {phys['jax'] / c_rate:.2f} (the bound for the "
        f"learning loop on one device); learning loop on 1 device / MJX physics only = "
        f"{one / phys['jax']:.2f}"
    )
    print(
        f"  the learner updated its weights in {100 * loop.learning_share:.1f}% of the run-steps "
        f"(the catching task learns only while the cube is inside the virtual sphere, "
        f"{100 * loop.inside_share:.1f}% of the run-steps)"
    )
    for variant in variants[1:]:
        diff = np.abs(loop.peaks[variant] - loop.peaks[first])
        print(
            f"  {variant} / {first} network step: {loop.rates[variant, n1] / one:.2f}"
            f" (1 device); peak contact force per run differs by at most {diff.max():.3g} N "
            f"(median {np.median(diff):.2g} N, largest peak {loop.peaks[first].max():.3g} N)"
        )
    if cfg.warp:
        print(
            f"  MuJoCo Warp physics only / mujoco.rollout = {phys['warp'] / c_rate:.2f}; "
            f"/ MJX physics only = {phys['warp'] / phys['jax']:.2f}"
        )
    if grad_ratio is not None:
        print(f"  exact gradient / forward rollout (catching, 1 device) = {grad_ratio:.2f}")
    for variant in variants:
        for n in loop.counts:
            rate, speedup = loop.rates[variant, n], loop.rates[variant, n] / loop.rates[variant, n1]
            print(
                f"  {n} device(s), {variant} network step: learning loop / mujoco.rollout = "
                f"{rate / c_rate:.2f}, speed-up over 1 device = {speedup:.2f}"
            )


if __name__ == "__main__":
    main()
