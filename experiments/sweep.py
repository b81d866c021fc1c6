"""Sweep over pendulum conditions and seeds with the online learning inside (``vmap``).

    python experiments/sweep.py --out runs/sweep --seed 0
    python experiments/sweep.py --out runs/sweep --shard-index 0 --num-shards 4   # one of 4 hosts
    python experiments/sweep.py --out runs/sweep --merge-only                      # merge shards

The grid is the product of the listed rod lengths, cube masses, release angles, hinge dampings and
arrival phases, times ``--seeds`` network initialisations. Each run is one catching experiment
(``experiments/task_loop.py``): ``--swings`` swings with the weights carried over, plus the plain
impedance baseline (F_o = 0) under the same condition. Runs are processed in chunks of ``--chunk``
(one ``vmap``); each finished chunk is written atomically to ``chunks/chunk_NNNNN.npz``, and a
restarted sweep skips the chunks already there, so an interrupted sweep loses at most one chunk; it
must be restarted with the same arguments (checked against ``chunks/sweep_settings.json``).
With several devices (GPUs of one host, or CPU devices forced with
``XLA_FLAGS=--xla_force_host_platform_device_count=N``) each device runs its slice of every chunk
with its own executable, called from its own thread (``experiments.devices.OnDevices``;
``--spmd``: one GSPMD program instead) where ``--chunk`` divides by the device count (otherwise
one device runs, with a message; ``shard_*/timing.json`` records the count used); across hosts,
``--shard-index/--num-shards`` take every n-th chunk and ``--merge-only`` merges the chunk files
afterwards. Writes ``config.json``, ``metrics.json`` (success rate, peak force ratio
learned/plain) and ``peak_ratio_map.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

if "--float32" not in sys.argv:  # float64 unless asked (before any array is made)
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from experiments import task_loop as tl  # noqa: E402
from experiments.devices import OnDevices, Sharded  # noqa: E402
from hec_jax.mjx_scene import PendulumConditions  # noqa: E402
from hec_jax.runs import (  # noqa: E402
    enable_compile_cache,
    save_figure,
    start_run,
    write_json,
    write_npz,
)

FIELDS = PendulumConditions._fields


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    tl.add_common_args(p, "runs/sweep")
    p.add_argument("--rod-length", type=float, nargs="+", default=[0.5, 0.6, 0.7], help="[m]")
    p.add_argument("--cube-mass", type=float, nargs="+", default=[0.5, 0.7, 0.9], help="[kg]")
    p.add_argument("--release-angles", type=float, nargs="+", default=[-0.45, -0.5, -0.55])
    p.add_argument("--release-speed", type=float, nargs="+", default=[0.0], help="[rad/s]")
    p.add_argument("--hinge-damping", type=float, nargs="+", default=[0.002], help="[N m s/rad]")
    p.add_argument("--arrival-phase", type=float, nargs="+", default=[0.0], help="[s]")
    p.add_argument("--swings", type=int, default=6)
    p.add_argument("--swing-s", type=float, default=1.5, help="duration of one swing [s]")
    p.add_argument("--mu", type=float, default=1e-3)
    p.add_argument("--f-cd", type=float, default=1.0, help="desired contact force F_cd [N]")
    p.add_argument("--chunk", type=int, default=16, help="runs per vmapped chunk")
    p.add_argument("--float32", action="store_true", help="float32 (default float64)")
    p.add_argument(
        "--solver-iterations",
        type=int,
        nargs=2,
        default=None,
        metavar=("ITER", "LS_ITER"),
        help="cap MuJoCo's opt.iterations / opt.ls_iterations (default: scene.xml's 100 / 50)",
    )
    p.add_argument(
        "--solver",
        choices=("newton", "cg"),
        default=None,
        help="MuJoCo's opt.solver (default: scene.xml's Newton)",
    )
    p.add_argument(
        "--jacobian",
        choices=("dense", "sparse"),
        default=None,
        help="MuJoCo's opt.jacobian (default: scene.xml's auto = dense); cg + sparse is the "
        "fastest on a GPU, with --solver-iterations 8 8 or more (CG below 8 iterations changed "
        "learned runs)",
    )
    p.add_argument("--shard-index", type=int, default=0)
    p.add_argument("--num-shards", type=int, default=1)
    p.add_argument("--merge-only", action="store_true")
    p.add_argument(
        "--spmd",
        action="store_true",
        help="several devices as one SPMD program (NamedSharding under jit, GSPMD) instead of one "
        "executable per device (experiments/devices.py); not with --kernel triton on GPUs",
    )
    args = p.parse_args(argv)
    if not 0 <= args.shard_index < args.num_shards:
        raise SystemExit("need 0 <= --shard-index < --num-shards")
    if args.chunk < 1:
        raise SystemExit("--chunk must be >= 1")
    return args


def grid(args) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Flattened grid: condition fields (N,) each and the seed index (N,) of every run."""
    axes = [
        args.rod_length,
        args.cube_mass,
        args.release_angles,
        args.release_speed,
        args.hinge_damping,
        args.arrival_phase,
        list(range(args.seeds)),
    ]
    rows = np.array(list(itertools.product(*axes)), dtype=float)
    conditions = {name: rows[:, i] for i, name in enumerate(FIELDS)}
    return conditions, rows[:, -1].astype(int)


def make_summary(config, sweep):
    """``run(keys, switches, conditions) -> per-run metrics`` (not jitted): the swing logs are reduced
    on the device (peak |F_int| per swing [N], smallest Eq. 49 margins, settle force [N]), so only
    a few numbers per run leave it."""
    settle = int(round(0.3 / config.controller.dt))  # last 0.3 s of the last swing

    def run(keys, sw, conditions):
        logs = sweep(keys, sw, conditions)
        force = jnp.linalg.norm(logs["f_contact"][..., jnp.array([0, 2])], axis=-1)  # (B, S, T)
        return dict(
            peak_per_swing=force.max(-1),
            min_margin=logs["margins"].min(axis=(1, 2)),  # (B, 3)
            settle_force=force[:, -1, -settle:].mean(-1),
        )

    return run


def unique_conditions(conditions: dict[str, np.ndarray], size: int):
    """The distinct conditions among a chunk's runs, padded to ``size`` rows (a fixed shape for
    one compile), and for every run the row of its condition. Plain impedance does not use the
    networks, so its result depends on the condition only, not on the seed."""
    table = np.stack([conditions[k] for k in FIELDS], axis=1)
    rows, inverse = np.unique(table, axis=0, return_inverse=True)
    if len(rows) > size:
        raise ValueError(f"{len(rows)} distinct conditions do not fit in {size} rows")
    rows = np.concatenate([rows, np.repeat(rows[-1:], size - len(rows), axis=0)])
    return {k: rows[:, i] for i, k in enumerate(FIELDS)}, inverse.reshape(-1)


def plain_rows(chunk: int, seeds: int, n_dev: int) -> int:
    """Rows of the plain batch: distinct conditions a chunk of consecutive runs can hold (seeds
    are the fastest grid axis), rounded up to a multiple of the device count."""
    rows = min(chunk, -(-chunk // seeds) + 1)
    return -(-rows // n_dev) * n_dev


def chunk_inputs(keys, conditions, n_plain):
    """One batch for a chunk: its learned runs, then its distinct conditions under plain impedance
    (the first key; plain ignores the networks), so both share one compiled function. Returns the
    arguments of ``make_summary``'s function and, for every run, the row of its plain result."""
    plain_cond, inverse = unique_conditions(conditions, n_plain)
    n = len(keys)

    learned, plain = tl.switches("learned"), tl.switches("plain")
    sw = learned._replace(
        use_virtual=np.r_[np.full(n, learned.use_virtual), np.full(n_plain, plain.use_virtual)],
        learn=np.r_[np.full(n, learned.learn), np.full(n_plain, plain.learn)],
    )
    all_keys = np.concatenate([np.asarray(keys), np.repeat(np.asarray(keys[:1]), n_plain, 0)])
    both = PendulumConditions(**{k: np.r_[conditions[k], plain_cond[k]] for k in conditions})
    return (all_keys, sw, both), n + inverse


def run_chunk(run, placed, rows_plain):
    """Per-run metrics of one chunk from ``run`` (``OnDevices``) on its placed ``chunk_inputs``."""
    out = run.run(placed)
    n = len(rows_plain)
    plain = {k: v[rows_plain] for k, v in out.items()}
    learned = {k: v[:n] for k, v in out.items()}
    return dict(
        peak_plain_per_swing=plain["peak_per_swing"],
        peak_learned_per_swing=learned["peak_per_swing"],
        min_margin=learned["min_margin"],
        settle_force=learned["settle_force"],
        peak_plain=plain["peak_per_swing"][:, 0],
        peak_learned=learned["peak_per_swing"][:, -1],
    )


# arguments that do not change a chunk's results (where it is computed, and how it is merged)
PLACEMENT_ARGS = ("out", "shard_index", "num_shards", "merge_only", "spmd")


def check_same_sweep(chunk_dir: Path, args, n_runs: int, n_chunks: int) -> None:
    """Refuses to resume (or add a shard to) a sweep whose chunks were computed with other settings.

    The first process writes ``chunks/sweep_settings.json`` (atomically); a later one with other
    grid, learner, solver or chunk settings would otherwise mix chunks of two sweeps in one folder.
    """
    settings = {k: v for k, v in sorted(vars(args).items()) if k not in PLACEMENT_ARGS}
    settings = json.loads(json.dumps(dict(settings, n_runs=n_runs, n_chunks=n_chunks)))
    path = chunk_dir / "sweep_settings.json"
    if path.exists():
        before = json.loads(path.read_text())
        if before != settings:
            diff = {
                k: (before.get(k), settings.get(k))
                for k in sorted(set(before) | set(settings))
                if before.get(k) != settings.get(k)
            }
            raise SystemExit(
                f"{path} belongs to a sweep with other settings (before, now): {diff}; "
                "resume with the same arguments, or use another --out"
            )
    else:
        write_json(path, settings)


def main(argv=None):
    args = parse(argv)
    enable_compile_cache()
    conditions, seed_index = grid(args)
    n_runs = len(seed_index)
    n_chunks = -(-n_runs // args.chunk)
    settings = dict(
        {k: v for k, v in vars(args).items() if k != "seed"},
        n_runs=n_runs,
        n_chunks=n_chunks,
        devices=[str(d) for d in jax.devices()],
    )
    folder = Path(args.out)
    chunk_dir = folder / "chunks"
    if not args.merge_only:
        check_same_sweep(chunk_dir, args, n_runs, n_chunks)
        start_run(folder / f"shard_{args.shard_index}", args.seed, settings)
        learner = tl.learner_from_args(args, "catching", args.f_cd)
        config = tl.config_from_args(args, learner, args.swing_s, args.swings)
        if args.solver_iterations is not None:
            config = dataclasses.replace(
                config,
                solver_iterations=args.solver_iterations[0],
                ls_iterations=args.solver_iterations[1],
            )
        config = dataclasses.replace(config, solver=args.solver, jacobian=args.jacobian)
        n_dev = jax.device_count()
        devices = jax.devices()[:1]
        if n_dev > 1 and args.chunk % n_dev == 0:  # each device runs its slice of every chunk
            devices = jax.devices()
        elif n_dev > 1:
            print(
                f"--chunk {args.chunk} does not divide by the {n_dev} devices: one device runs it",
                flush=True,
            )
        strategy = OnDevices
        if args.spmd and len(devices) > 1:
            if args.kernel == "triton" and jax.default_backend() == "gpu":
                raise SystemExit(
                    "--spmd with --kernel triton: GSPMD cannot split the Triton kernel (a custom "
                    "call without a partitioning rule); leave out --spmd"
                )
            strategy = Sharded
        n_plain = plain_rows(args.chunk, args.seeds, len(devices))
        run = strategy(
            make_summary(config, tl.make_sweep(config, per_run_switches=True)),
            devices,
            tl.sweep_in_axes(per_run_switches=True),
        )
        all_keys = jax.random.split(jax.random.PRNGKey(args.seed), args.seeds)
        mine = [c for c in range(n_chunks) if c % args.num_shards == args.shard_index]
        t_start = time.perf_counter()
        done, compile_s = 0, 0.0
        for c in mine:
            path = chunk_dir / f"chunk_{c:05d}.npz"
            if path.exists():
                print(f"chunk {c + 1}/{n_chunks}: already there, skipped", flush=True)
                continue
            index = np.arange(c * args.chunk, min((c + 1) * args.chunk, n_runs))
            padded = np.concatenate([index, np.full(args.chunk - len(index), index[-1])])
            t0 = time.perf_counter()
            inputs, rows_plain = chunk_inputs(
                all_keys[seed_index[padded]],
                {k: v[padded] for k, v in conditions.items()},
                n_plain,
            )
            placed = run.place(*inputs)
            if not done:  # compile ahead of time (every chunk has the same shapes), timed apart
                run.compile(placed)
                compile_s = time.perf_counter() - t0
            res = run_chunk(run, placed, rows_plain)
            res = {k: v[: len(index)] for k, v in res.items()}
            write_npz(
                path,
                index=index,
                seed_index=seed_index[index],
                **res,
                **{k: v[index] for k, v in conditions.items()},
            )
            done += 1
            elapsed = time.perf_counter() - t_start
            left = sum(not (chunk_dir / f"chunk_{k:05d}.npz").exists() for k in mine)
            print(
                f"chunk {c + 1}/{n_chunks} ({len(index)} runs) in {time.perf_counter() - t0:.1f} s;"
                f" {left} left in this shard, about {elapsed / done * left:.0f} s",
                flush=True,
            )
        if done:
            wall = time.perf_counter() - t_start
            print(
                f"{done} chunks in {wall:.1f} s, compilation ({compile_s:.1f} s) included",
                flush=True,
            )
            write_json(
                folder / f"shard_{args.shard_index}" / "timing.json",
                {
                    "chunks_run": done,
                    "wall_s": wall,
                    "compile_s": compile_s,
                    "runs_per_chunk": args.chunk,
                    "devices_used": [str(d) for d in devices],
                    "multi_device": "gspmd" if strategy is Sharded else "executable per device",
                    "plain_rows_per_chunk": n_plain,
                },
            )
    return merge(folder, chunk_dir, conditions, seed_index, n_chunks, args)


def merge(folder, chunk_dir, conditions, seed_index, n_chunks, args) -> dict:
    """Merges whatever chunk files exist into ``metrics.json`` and the map."""
    files = sorted(chunk_dir.glob("chunk_*.npz"))
    if not files:
        print("no chunk files yet")
        return {}
    parts = [dict(np.load(f)) for f in files]
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(data["index"])
    data = {k: v[order] for k, v in data.items()}
    # Conditions where the swing never reaches the waiting hand have nothing to catch.
    reached = data["peak_plain"] > 1.0  # [N]
    ratio = np.where(
        reached, data["peak_learned"] / np.where(reached, data["peak_plain"], 1.0), np.nan
    )
    success = ratio[reached] <= 0.5
    metrics = {
        "runs_done": int(len(order)),
        "runs_total": int(len(seed_index)),
        "chunks_done": len(files),
        "chunks_total": n_chunks,
        "runs_without_contact_in_plain": int((~reached).sum()),
        "success_rate_peak_at_most_half_plain": float(success.mean()) if success.size else None,
        "peak_ratio_learned_over_plain": tl.mean_std(ratio[reached]) if reached.any() else None,
        "strictly_stable_every_run": bool(np.all(data["min_margin"] > 0)),
        "per_run": [
            {
                **{k: float(data[k][i]) for k in FIELDS},
                "seed_index": int(data["seed_index"][i]),
                "peak_plain": float(data["peak_plain"][i]),
                "peak_learned": float(data["peak_learned"][i]),
            }
            for i in range(len(order))
        ],
    }
    write_json(folder / "metrics.json", metrics)
    plot_map(folder, data, ratio)
    print(
        f"merged {len(order)}/{len(seed_index)} runs ({int((~reached).sum())} never reach the "
        f"hand): success {np.mean(success):.0%}, peak ratio learned/plain "
        f"{np.nanmean(ratio):.2f} +- {np.nanstd(ratio):.2f}"
    )
    return metrics


def plot_map(folder, data, ratio):
    """Mean learned/plain peak ratio over the two swept condition axes with most values."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    swept = sorted(FIELDS, key=lambda k: -len(np.unique(data[k])))[:2]
    xs, ys = (np.unique(data[k]) for k in swept)
    grid_ratio = np.full((len(ys), len(xs)), np.nan)
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            sel = (data[swept[0]] == x) & (data[swept[1]] == y)
            if np.any(sel & np.isfinite(ratio)):
                grid_ratio[j, i] = np.nanmean(ratio[sel])
    fig, ax = plt.subplots(figsize=(5, 4))
    im = ax.imshow(grid_ratio, origin="lower", aspect="auto", cmap="viridis")
    ax.set_xticks(range(len(xs)), [f"{x:.3g}" for x in xs])
    ax.set_yticks(range(len(ys)), [f"{y:.3g}" for y in ys])
    ax.set(xlabel=swept[0], ylabel=swept[1], title="peak force learned / plain (mean)")
    fig.colorbar(im)
    save_figure(fig, folder / "peak_ratio_map.png")
    plt.close(fig)


if __name__ == "__main__":
    main()
