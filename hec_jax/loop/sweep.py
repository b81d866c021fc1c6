"""Catching over a grid of pendulum conditions and seeds, with the online learning inside.

The grid is the product of the listed values of every :class:`~hec_jax.mjx_scene.PendulumConditions`
field (named, :class:`SweepGrid`), times ``seeds`` network initialisations. Each run is one
catching experiment (``config.task``: swings with the weights carried over) plus the plain
impedance baseline (F_o = 0) under the same condition. Runs are processed in chunks of ``chunk``
(one ``vmap``); each finished chunk is written atomically to ``chunks/chunk_NNNNN.npz`` and a
restarted sweep skips the chunks already there (it must have the same settings:
``chunks/sweep_settings.json``; every chunk carries the hash of the settings it was computed
under, and a chunk of other settings is never merged). With several devices each device runs its slice of every chunk
(:mod:`hec_jax.loop.devices`); across hosts, ``shard_index/num_shards`` take every n-th chunk and
:func:`merge` merges the chunk files afterwards.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.loop.config import TaskConfig, sweep_catching
from hec_jax.loop.devices import OnDevices, Sharded
from hec_jax.loop.episodes import make_sweep, sweep_in_axes
from hec_jax.loop.metrics import mean_std
from hec_jax.loop.policy import build_loop, switches
from hec_jax.mjx_scene import PendulumConditions, PendulumConfig, validate_conditions
from hec_jax.mjx_scene.model import scene_hinge_x
from hec_jax.progress import ProgressBar, format_seconds
from hec_jax.runs import save_figure, start_run, write_json, write_npz

FIELDS = PendulumConditions._fields
# the grid's field (plural) of each pendulum field (by name, never by position)
GRID_FIELD = {
    "rod_length": "rod_lengths",
    "cube_mass": "cube_masses",
    "release_angle": "release_angles",
    "release_speed": "release_speeds",
    "hinge_damping": "hinge_dampings",
    "arrival_phase": "arrival_phases",
    "hinge_x": "hinge_xs",
}


@dataclass(frozen=True)
class SweepGrid:
    """The values of each pendulum field the sweep takes (the grid is their product)."""

    rod_lengths: tuple[float, ...] = (0.5, 0.6, 0.7)  # [m]
    cube_masses: tuple[float, ...] = (0.5, 0.7, 0.9)  # [kg]
    release_angles: tuple[float, ...] = (-0.45, -0.5, -0.55)  # [rad]
    release_speeds: tuple[float, ...] = (0.0,)  # [rad/s]
    hinge_dampings: tuple[float, ...] = (0.002,)  # [N m s/rad]
    arrival_phases: tuple[float, ...] = (0.0,)  # [s]
    hinge_xs: tuple[float, ...] | None = None  # [m]; None: scene.xml's hinge

    def __post_init__(self):
        assert set(GRID_FIELD) == set(FIELDS)
        for name in GRID_FIELD.values():
            v = getattr(self, name)
            if v is not None and len(v) == 0:
                raise ValueError(f"SweepGrid.{name} needs at least one value")
        table = self.table()
        validate_conditions(PendulumConditions(**{k: table[:, i] for i, k in enumerate(FIELDS)}))

    def values(self, name: str) -> tuple[float, ...]:
        """The values of pendulum field ``name`` (hinge_x None: scene.xml's)."""
        v = getattr(self, GRID_FIELD[name])
        return (scene_hinge_x(),) if v is None else tuple(v)

    def table(self) -> np.ndarray:
        """(n_conditions, n_fields) every combination, fields in ``FIELDS`` order (by name)."""
        return np.array(list(itertools.product(*(self.values(k) for k in FIELDS))), dtype=float)


@dataclass(frozen=True)
class SweepConfig:
    """A sweep: the task of each run, the grid, seeds and how chunks are computed."""

    task: TaskConfig = field(default_factory=sweep_catching)
    grid: SweepGrid = field(default_factory=SweepGrid)
    seed: int = 0  # PRNG seed of the network initialisations
    seeds: int = 5  # network initialisations per condition
    chunk: int = 16  # runs per vmapped chunk
    float32: bool = False  # float32 (default float64)
    # several devices as one GSPMD program (NamedSharding under jit) instead of one executable
    # per device; not with the Triton kernel on GPUs
    spmd: bool = False

    def __post_init__(self):
        for name in ("seeds", "chunk"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"SweepConfig.{name} must be an integer >= 1, got {v}")
        if self.task.learner.task != "catching" or self.task.final_s:
            raise ValueError("the sweep runs catching tasks without a continuous run")
        if self.task.pendulum != PendulumConfig():
            raise ValueError(
                "the sweep's pendulum conditions come from its grid (--rod-lengths, "
                "--cube-masses, ...), not from the task's pendulum fields"
            )

    def runs(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Flattened grid: condition fields (N,) each and the seed index (N,) of every run
        (seeds are the fastest axis).
        """
        table = self.grid.table()
        rows = np.repeat(table, self.seeds, axis=0)
        seed_index = np.tile(np.arange(self.seeds), len(table))
        return {k: rows[:, i] for i, k in enumerate(FIELDS)}, seed_index

    def settings(self) -> dict:
        """What decides a chunk's results (checked on resume and merge), as JSON values."""
        conditions, seed_index = self.runs()
        n = len(seed_index)
        out = dict(dataclasses.asdict(self), spmd=None, n_runs=n, n_chunks=-(-n // self.chunk))
        return json.loads(json.dumps(out))


def make_summary(loop, sweep):
    """``run(keys, switches, conditions) -> per-run metrics`` (not jitted): the swing logs are
    reduced on the device (peak |F_int| per swing [N], smallest Eq. 49 margins, settle force [N]),
    so only a few numbers per run leave it.
    """
    settle = int(round(loop.config.settle_s / loop.ids.timestep))  # the last swing's last part

    def run(keys, sw, conditions):
        logs = sweep(keys, sw, conditions)
        force = jnp.linalg.norm(logs["f_contact"][..., jnp.array([0, 2])], axis=-1)  # (B, S, T)
        return dict(
            peak_per_swing=force.max(-1),
            min_margin=logs["margins"].min(axis=(1, 2)),  # (B, 3)
            settle_force=force[:, -1, -settle:].mean(-1),
            finite=jnp.all(jnp.isfinite(force), axis=(1, 2)),
        )

    return run


def unique_conditions(conditions: dict[str, np.ndarray], size: int):
    """The distinct conditions among a chunk's runs, padded to ``size`` rows (a fixed shape for
    one compile), and for every run the row of its condition. Plain impedance does not use the
    networks, so its result depends on the condition only, not on the seed.
    """
    table = np.stack([conditions[k] for k in FIELDS], axis=1)
    rows, inverse = np.unique(table, axis=0, return_inverse=True)
    if len(rows) > size:
        raise ValueError(f"{len(rows)} distinct conditions do not fit in {size} rows")
    rows = np.concatenate([rows, np.repeat(rows[-1:], size - len(rows), axis=0)])
    return {k: rows[:, i] for i, k in enumerate(FIELDS)}, inverse.reshape(-1)


def plain_rows(chunk: int, seeds: int, n_dev: int) -> int:
    """Rows of the plain batch: distinct conditions a chunk of consecutive runs can hold (seeds
    are the fastest grid axis), rounded up to a multiple of the device count.
    """
    rows = min(chunk, -(-chunk // seeds) + 1)
    return -(-rows // n_dev) * n_dev


def chunk_inputs(keys, conditions, n_plain):
    """One batch for a chunk: its learned runs, then its distinct conditions under plain impedance
    (the first key; plain ignores the networks), so both share one compiled function. Returns the
    arguments of ``make_summary``'s function and, for every run, the row of its plain result.
    """
    plain_cond, inverse = unique_conditions(conditions, n_plain)
    n = len(keys)
    learned, plain = switches("learned"), switches("plain")
    sw = learned._replace(
        use_virtual=np.r_[np.full(n, learned.use_virtual), np.full(n_plain, plain.use_virtual)],
        learn=np.r_[np.full(n, learned.learn), np.full(n_plain, plain.learn)],
    )
    all_keys = np.concatenate([np.asarray(keys), np.repeat(np.asarray(keys[:1]), n_plain, 0)])
    both = PendulumConditions(**{k: np.r_[conditions[k], plain_cond[k]] for k in FIELDS})
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
        finite_plain=plain["finite"],
        finite_learned=learned["finite"],
    )


def check_same_sweep(chunk_dir: Path, config: SweepConfig) -> None:
    """Refuses to resume (or add a shard to, or merge) a sweep whose chunks were computed with
    other settings: the first process writes ``chunks/sweep_settings.json`` (atomically).

    Raises:
        SystemExit: with the differing settings (before, now).
    """
    settings = config.settings()
    path = chunk_dir / "sweep_settings.json"
    if path.exists() and not any(chunk_dir.glob("chunk_*.npz")):
        # nothing computed under those settings yet: a corrected call may start over (shards
        # starting together may race here: another may have removed or rewritten it already)
        path.unlink(missing_ok=True)
    try:
        before = json.loads(path.read_text())  # written atomically: whole or absent
    except FileNotFoundError:
        before = None
    if before is not None:
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


CHUNK_KEYS = (
    "index",
    "seed_index",
    "peak_plain",
    "peak_learned",
    "min_margin",
    "settle_force",
    "finite_plain",
    "finite_learned",
)


def settings_sha256(config: SweepConfig) -> str:
    """The SHA-256 of :meth:`SweepConfig.settings` (keys sorted): written into every chunk, so
    that a chunk is only ever merged into the sweep that computed it.
    """
    text = json.dumps(config.settings(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def chunk_sweep(path: Path) -> str | None:
    """The ``settings_sha256`` a chunk file was computed under (None: unreadable or none;
    "mixed" if its runs disagree).
    """
    try:
        with np.load(path) as data:
            shas = set(np.atleast_1d(data["settings_sha256"]).astype(str).tolist())
    except Exception:  # noqa: BLE001
        return None
    return shas.pop() if len(shas) == 1 else "mixed"


def chunk_is_complete(path: Path, n_runs: int | None = None) -> bool:
    """Whether ``path`` is a readable chunk file with every array the merge needs and the
    sweep's settings hash (and ``n_runs`` runs when given); a damaged or truncated file is not.
    """
    try:
        with np.load(path) as data:
            arrays = {k: data[k] for k in CHUNK_KEYS}
            arrays["settings_sha256"] = data["settings_sha256"]
    except Exception:  # noqa: BLE001 (any failure to read means: not done)
        return False
    n = len(arrays["index"])
    return all(len(v) == n for v in arrays.values()) and (n_runs is None or n == n_runs)


def _refuse_other_sweeps(files, config: SweepConfig) -> None:
    """Refuses chunk files computed under other settings than ``config``'s (e.g. by a shard
    started with other arguments while this one compiled, before either wrote a chunk).

    Raises:
        SystemExit: naming them.
    """
    sha = settings_sha256(config)
    other = [str(f) for f in files if chunk_sweep(f) not in (sha, None)]
    if other:
        raise SystemExit(
            f"chunk files computed with other settings than this sweep's: {other}; resume with"
            " the same arguments as those, or use another --out"
        )


def _keep_earlier_records(shard_dir: Path) -> None:
    """Moves a shard's earlier ``config.json`` and ``timing.json`` (a resumed or repeated
    shard, perhaps on another machine or commit) into ``shard_dir/earlier/`` under their start
    time, so that the record of who computed the chunks already there is kept.
    """
    config = shard_dir / "config.json"
    if not config.exists():
        return
    try:
        started = json.loads(config.read_text()).get("started_utc", "unknown")
    except ValueError:
        started = "unreadable"
    stamp = str(started).replace(":", "").replace("-", "")
    earlier = shard_dir / "earlier"
    earlier.mkdir(exist_ok=True)
    for n in itertools.count(1):
        target = earlier / (stamp if n == 1 else f"{stamp}-{n}")
        try:
            target.mkdir()
            break
        except FileExistsError:
            continue
    for name in ("config.json", "timing.json"):
        if (shard_dir / name).exists():
            os.replace(shard_dir / name, target / name)


def run_sweep(
    config: SweepConfig,
    folder: Path,
    shard_index: int = 0,
    num_shards: int = 1,
    run_settings: dict | None = None,
    progress: bool = True,
) -> dict:
    """Computes this shard's missing chunks into ``folder/chunks`` and merges what exists.

    Returns the merged metrics (:func:`merge`). ``run_settings``: recorded in the shard's
    ``config.json`` beside the sweep's settings (e.g. the command line). ``progress``: a bar over
    the runs still to compute (:class:`~hec_jax.progress.ProgressBar`: elapsed and remaining
    time), the compile time on its own line.
    """
    if not 0 <= shard_index < num_shards:
        raise ValueError(f"need 0 <= shard_index < num_shards, got {shard_index}, {num_shards}")
    if jax.config.jax_enable_x64 == config.float32:
        raise ValueError(
            f"SweepConfig.float32 is {config.float32} but jax_enable_x64 is"
            f" {jax.config.jax_enable_x64}: call jax.config.update('jax_enable_x64',"
            " not config.float32) first (the chunks would be computed in the other precision)"
        )
    conditions, seed_index = config.runs()
    n_runs = len(seed_index)
    n_chunks = -(-n_runs // config.chunk)
    chunk_dir = folder / "chunks"
    check_same_sweep(chunk_dir, config)
    _refuse_other_sweeps(sorted(chunk_dir.glob("chunk_*.npz")), config)
    sha = settings_sha256(config)
    settings = dict(
        sweep=config.settings(), **(run_settings or {}), devices=[str(d) for d in jax.devices()]
    )
    shard_dir = folder / f"shard_{shard_index}"
    _keep_earlier_records(shard_dir)
    start_run(shard_dir, config.seed, settings)
    loop = build_loop(config.task)
    n_dev = jax.device_count()
    devices = jax.devices()[:1]
    if n_dev > 1 and config.chunk % n_dev == 0:  # each device runs its slice of every chunk
        devices = jax.devices()
    elif n_dev > 1:
        print(f"chunk {config.chunk} does not divide by the {n_dev} devices: one device runs it")
    strategy = OnDevices
    if config.spmd and len(devices) > 1:
        if config.task.learner.kernel == "triton" and jax.default_backend() == "gpu":
            raise SystemExit(
                "spmd with the triton kernel: GSPMD cannot split the Triton kernel (a custom "
                "call without a partitioning rule); leave out --spmd"
            )
        strategy = Sharded
    n_plain = plain_rows(config.chunk, config.seeds, len(devices))
    run = strategy(
        make_summary(loop, make_sweep(loop, per_run_switches=True)),
        devices,
        sweep_in_axes(per_run_switches=True),
    )
    all_keys = jax.random.split(jax.random.PRNGKey(config.seed), config.seeds)
    mine = [c for c in range(n_chunks) if c % num_shards == shard_index]

    def runs_of(c: int) -> np.ndarray:
        return np.arange(c * config.chunk, min((c + 1) * config.chunk, n_runs))

    todo = []
    for c in mine:
        path = chunk_dir / f"chunk_{c:05d}.npz"
        if path.exists() and chunk_is_complete(path, len(runs_of(c))):
            continue
        if path.exists():
            print(f"chunk {c + 1}/{n_chunks}: {path} is damaged, computed again", flush=True)
        todo.append(c)
    if len(todo) < len(mine):
        print(
            f"{len(mine) - len(todo)} of this shard's {len(mine)} chunks already there, skipped",
            flush=True,
        )

    def prepare(c: int):
        """Chunk ``c``'s inputs, placed on the devices (host work: runs while a chunk computes)."""
        index = runs_of(c)
        padded = np.concatenate([index, np.full(config.chunk - len(index), index[-1])])
        inputs, rows_plain = chunk_inputs(
            all_keys[seed_index[padded]], {k: v[padded] for k, v in conditions.items()}, n_plain
        )
        return index, rows_plain, run.place(*inputs)

    def save(path: Path, index: np.ndarray, res: dict) -> None:
        write_npz(
            path,
            index=index,
            seed_index=seed_index[index],
            settings_sha256=np.full(len(index), sha),  # per run, as every chunk array
            **res,
            **{k: v[index] for k, v in conditions.items()},
        )

    # The host's share of a chunk (its inputs, placing them, writing its file) overlaps the
    # devices' work on the chunk before: one thread prepares the next chunk, one writes the last;
    # each chunk is still written atomically and in order (docs/benchmarks_gpu.md, "Four GPUs").
    t_start = time.perf_counter()
    done, compile_s = 0, 0.0
    total = max(sum(len(runs_of(c)) for c in todo), 1)
    with (
        ProgressBar(total, "runs", enabled=progress and bool(todo)) as bar,
        ThreadPoolExecutor(max_workers=2) as pool,
    ):
        upcoming = pool.submit(prepare, todo[0]) if todo else None
        writing = None
        for i, c in enumerate(todo):
            bar.update(
                description=f"chunk {c + 1}/{n_chunks}" + (" (compiling)" if not done else "")
            )
            t0 = time.perf_counter()
            index, rows_plain, placed = upcoming.result()
            if i + 1 < len(todo):
                upcoming = pool.submit(prepare, todo[i + 1])
            if not done:  # compile ahead of time (every chunk has the same shapes), timed apart
                run.compile(placed)
                compile_s = time.perf_counter() - t0
                bar.log(f"compiled in {compile_s:.1f} s")
                bar.update(description=f"chunk {c + 1}/{n_chunks}")
            res = run_chunk(run, placed, rows_plain)
            del placed
            res = {k: v[: len(index)] for k, v in res.items()}
            if writing is not None:
                writing.result()  # the chunk before is on disk (and its errors raised) first
            writing = pool.submit(save, chunk_dir / f"chunk_{c:05d}.npz", index, res)
            done += 1
            bar.update(len(index))
        if writing is not None:
            writing.result()
    if done:
        wall = time.perf_counter() - t_start
        print(
            f"{done} chunks in {format_seconds(wall)}: compile {compile_s:.1f} s, run"
            f" {wall - compile_s:.1f} s",
            flush=True,
        )
        write_json(
            folder / f"shard_{shard_index}" / "timing.json",
            {
                "chunks_run": done,
                "wall_s": wall,
                "compile_s": compile_s,
                "runs_per_chunk": config.chunk,
                "devices_used": [str(d) for d in devices],
                "multi_device": "gspmd" if strategy is Sharded else "executable per device",
                "plain_rows_per_chunk": n_plain,
            },
        )
    return merge(folder, config)


def merge(folder: Path, config: SweepConfig) -> dict:
    """Merges whatever chunk files exist into ``metrics.json`` and ``peak_ratio_map.png`` (the
    settings are checked first). A run counts as diverged when any of its forces is not finite;
    "never reaches the hand" needs a finite plain run whose peak stays at or below 1 N; a
    success needs the learned peak at most half the plain one and the learned hand touching the
    cube (peak above 1 N). Damaged chunk files are named and refused.
    """
    chunk_dir = folder / "chunks"
    check_same_sweep(chunk_dir, config)
    _, seed_index = config.runs()
    files = sorted(chunk_dir.glob("chunk_*.npz"))
    _refuse_other_sweeps(files, config)
    damaged = [str(f) for f in files if not chunk_is_complete(f)]
    if damaged:
        raise SystemExit(f"damaged chunk files (run the sweep again to recompute them): {damaged}")
    if not files:
        print("no chunk files yet")
        return {}
    parts = [dict(np.load(f)) for f in files]
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(data["index"])
    data = {k: v[order] for k, v in data.items()}
    finite = data["finite_plain"] & data["finite_learned"]
    reached = finite & (data["peak_plain"] > 1.0)  # [N]; else nothing to catch
    ratio = np.where(
        reached, data["peak_learned"] / np.where(reached, data["peak_plain"], 1.0), np.nan
    )
    touched = data["peak_learned"] > 1.0  # [N]: the learned hand met the cube (not avoided it)
    success = (ratio <= 0.5)[reached] & touched[reached]
    metrics = {
        "runs_done": int(len(order)),
        "runs_total": int(len(seed_index)),
        "chunks_done": len(files),
        "chunks_total": config.settings()["n_chunks"],
        "runs_diverged": int((~finite).sum()),
        "runs_without_contact_in_plain": int((finite & ~reached).sum()),
        "runs_learned_never_touching": int((reached & ~touched).sum()),
        "success_rate_peak_at_most_half_plain": float(success.mean()) if success.size else None,
        "peak_ratio_learned_over_plain": mean_std(ratio[reached]) if reached.any() else None,
        # over the finite runs (the diverged ones are counted above); None: none finite
        "strictly_stable_every_run": (
            bool(np.all(data["min_margin"][finite] > 0)) if finite.any() else None
        ),
        "per_run": [
            {
                **{k: float(data[k][i]) for k in FIELDS},
                "seed_index": int(data["seed_index"][i]),
                "peak_plain": float(data["peak_plain"][i]),
                "peak_learned": float(data["peak_learned"][i]),
                "diverged": bool(not finite[i]),
            }
            for i in range(len(order))
        ],
    }
    write_json(folder / "metrics.json", metrics)
    plot_map(folder, data, ratio)
    print(
        f"merged {len(order)}/{len(seed_index)} runs ({metrics['runs_without_contact_in_plain']}"
        f" never reach the hand, {metrics['runs_diverged']} diverged): success "
        f"{np.mean(success):.0%}, peak ratio learned/plain "
        f"{np.nanmean(ratio):.2f} +- {np.nanstd(ratio):.2f}"
    )
    return metrics


def plot_map(folder: Path, data: dict, ratio: np.ndarray) -> None:
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
