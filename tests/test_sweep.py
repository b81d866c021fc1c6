"""The sweep: chunks written atomically, resume, shards across processes and devices."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "--rod-lengths", "0.6", "0.65", "--cube-masses", "0.7", "--release-angles", "-0.5",
    "--seeds", "1", "--swings", "2", "--swing-s", "0.7",
]  # fmt: skip


def _sweep(out, *extra, devices=1):
    env = dict(os.environ)
    env.setdefault("HEC_JAX_CACHE", str(ROOT / ".jax_cache"))
    if devices > 1:
        flags = env.get("XLA_FLAGS", "")
        env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
    proc = subprocess.run(
        [sys.executable, "experiments/sweep.py", "--out", str(out), *TINY, *extra],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def _tiny_sweep(*extra):
    """The SweepConfig that experiments/sweep.py builds from TINY (+ ``extra``)."""
    from hec_jax.cli import parse
    from hec_jax.loop.cli import SweepRun

    return parse(SweepRun(), [*TINY, *extra]).sweep


def _load(folder):
    files = sorted((Path(folder) / "chunks").glob("chunk_*.npz"))
    parts = [dict(np.load(f)) for f in files]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


@pytest.fixture(scope="module")
def sharded_by_process(tmp_path_factory):
    """Shard 0 of 2 in one process, then the whole sweep resumed in another (which finds shard 0's
    chunk and computes the rest): (folder, the chunks after shard 0, the resume's log, chunk 0's
    mtime before the resume). Two processes, not three (2026-12-03: each warm one takes about 20 s
    of the CI's time); a chunk computed twice, in two processes, is compared in the slow
    two-device test below."""
    out = tmp_path_factory.mktemp("sweep")
    _sweep(out, "--chunk", "1", "--shard-index", "0", "--num-shards", "2")
    after_shard = sorted(p.name for p in (out / "chunks").glob("chunk_*.npz"))
    mtime0 = (out / "chunks" / "chunk_00000.npz").stat().st_mtime_ns
    log = _sweep(out, "--chunk", "1")  # an interrupted sweep resumed, or the other shard's work
    return out, after_shard, log, mtime0


def test_shards_merge_and_resume(sharded_by_process):
    out, after_shard, log, mtime0 = sharded_by_process
    assert after_shard == ["chunk_00000.npz"]  # shard 0 of 2 takes every other chunk from 0
    assert "1 of this shard's 2 chunks already there, skipped" in log
    chunk0 = out / "chunks" / "chunk_00000.npz"
    assert chunk0.stat().st_mtime_ns == mtime0  # finished work is not redone
    # the resume (shard 0 of 1) kept the record of shard 0 of 2, which computed chunk 0
    (earlier,) = (out / "shard_0" / "earlier").iterdir()
    assert "--num-shards" in json.loads((earlier / "config.json").read_text())["argv"]
    assert json.loads((earlier / "timing.json").read_text())["chunks_run"] == 1
    assert json.loads((out / "shard_0" / "timing.json").read_text())["chunks_run"] == 1
    merged = _load(out)  # the chunks of two processes
    np.testing.assert_array_equal(merged["index"], [0, 1])
    assert np.all(merged["peak_plain"] > 100.0)  # the hard impact without learning
    assert np.all(merged["min_margin"] > 0.0)  # strict Eq. 49 in every run
    # resuming with other settings would mix two sweeps' chunks: refused before any work
    proc = subprocess.run(
        [sys.executable, "experiments/sweep.py", "--out", str(out), *TINY, "--chunk", "1",
         "--solver", "cg"],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode != 0 and "other settings" in proc.stderr
    assert "'task': " in proc.stderr and "'cg'" in proc.stderr
    assert chunk0.stat().st_mtime_ns == mtime0


@pytest.mark.parametrize(
    "spmd",
    [
        # slow: the sweep in two more processes; the default suite keeps tests/test_devices.py
        # (one executable per device on two forced devices, the GSPMD program on one)
        pytest.param(False, id="executable-per-device", marks=pytest.mark.slow),
        pytest.param(True, id="gspmd", marks=pytest.mark.slow),
    ],
)
def test_sharding_over_two_devices_matches(sharded_by_process, tmp_path, spmd):
    """Two forced CPU devices, one chunk of both runs split over them (one executable per device,
    or one GSPMD program with --spmd): the one-device results."""
    log = _sweep(tmp_path, "--chunk", "2", *(["--spmd"] if spmd else []), devices=2)
    assert "does not divide" not in log
    timing = json.loads((tmp_path / "shard_0" / "timing.json").read_text())
    assert len(timing["devices_used"]) == 2
    assert timing["multi_device"] == ("gspmd" if spmd else "executable per device")
    sharded, single = _load(tmp_path), _load(sharded_by_process[0])
    for k in ("peak_plain", "peak_learned", "min_margin", "settle_force"):
        np.testing.assert_allclose(sharded[k], single[k], rtol=1e-9, atol=1e-9, err_msg=k)


def test_a_chunk_with_its_plain_rows_divides_over_the_devices():
    from hec_jax.loop.sweep import plain_rows

    for chunk, seeds, n_dev in [(4, 2, 2), (6, 2, 2), (2, 1, 2), (12, 5, 4), (16, 3, 8)]:
        rows = plain_rows(chunk, seeds, n_dev)
        assert (chunk + rows) % n_dev == 0 if chunk % n_dev == 0 else rows % n_dev == 0
        assert rows >= min(chunk, -(-chunk // seeds) + 1)  # room for every distinct condition
    assert plain_rows(4, 2, 2) == 4 and plain_rows(6, 2, 1) == 4


@pytest.mark.slow  # compiles the sweep's summary in this process
def test_plain_runs_are_shared_across_seeds(sharded_by_process):
    """Plain impedance ignores the networks: the sweep runs it once per distinct condition. Run it
    here with two other network seeds and check both against the sweep's (seed-0) result."""
    import jax

    from hec_jax import loop as tl
    from hec_jax.loop import sweep
    from hec_jax.mjx_scene import PendulumConditions

    config = _tiny_sweep()
    lp = tl.build_loop(config.task)
    run = jax.jit(sweep.make_summary(lp, tl.make_sweep(lp)))
    conditions, _ = config.runs()
    first = _load(sharded_by_process[0])
    cond = PendulumConditions(**{k: np.repeat(conditions[k][1:2], 2) for k in conditions})
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    plain = np.asarray(run(keys, tl.switches("plain"), cond)["peak_per_swing"])
    np.testing.assert_allclose(plain, first["peak_plain_per_swing"][[1, 1]], rtol=1e-12)
    # and the distinct-condition table maps every run back to its own condition
    table, inverse = sweep.unique_conditions(
        {
            k: np.array([0.6, 0.6, 0.65, 0.6]) if k == "rod_length" else np.zeros(4)
            for k in conditions
        },
        3,
    )
    np.testing.assert_array_equal(table["rod_length"][inverse], [0.6, 0.6, 0.65, 0.6])
    with pytest.raises(ValueError, match="do not fit"):
        sweep.unique_conditions({k: np.arange(3.0) for k in conditions}, 2)


@pytest.mark.slow  # compiles the learned sweep in this process
def test_networks_inside_the_sphere_only_give_the_same_sweep(sharded_by_process):
    """``--nets-inside-only`` (O = 0 outside the virtual sphere, where Eq. 47 gives F_o = 0): the
    same learned peaks and settle forces as the sweep's default runs, in both swings."""
    import jax

    from hec_jax import loop as tl
    from hec_jax.loop import sweep
    from hec_jax.mjx_scene import PendulumConditions
    from hec_jax.nets.learner import NETS_SHELL

    config = _tiny_sweep("--no-nets-outside")
    learner = config.task.learner
    assert not learner.nets_outside
    lp = tl.build_loop(config.task)
    conditions, seed_index = config.runs()
    keys = jax.random.split(jax.random.PRNGKey(config.seed), config.seeds)[seed_index]
    cond = PendulumConditions(**{k: np.asarray(conditions[k]) for k in conditions})
    logs = jax.jit(tl.make_sweep(lp))(keys, tl.switches("learned"), cond)
    out = sweep.make_summary(lp, lambda *a: logs)(None, None, None)  # the sweep's reduction
    # the learner's wiring: K_o is 0 beyond the networks' shell past the sphere, not 0 inside it
    k_o, inside = np.asarray(logs["k_o"]), np.asarray(logs["inside"])  # (B, S, T, 2), (B, S, T)
    rho = np.linalg.norm(np.asarray(logs["x_o"]) - np.asarray(logs["x_e"]), axis=-1)
    active = rho <= learner.radius * (1.0 + NETS_SHELL)
    assert 0.05 < inside.mean() < 0.95
    np.testing.assert_array_equal(k_o[~active], 0.0)
    assert np.all(np.any(k_o[inside] != 0.0, axis=-1))
    first = _load(sharded_by_process[0])
    assert np.max(first["peak_learned_per_swing"]) > 1.0  # the runs make contact
    np.testing.assert_allclose(
        out["peak_per_swing"], first["peak_learned_per_swing"], rtol=1e-9, atol=1e-9
    )
    np.testing.assert_allclose(out["settle_force"], first["settle_force"], rtol=1e-9, atol=1e-9)


def test_damaged_chunks_and_a_folder_with_nothing_computed(tmp_path):
    """A truncated chunk file is not 'done' (and the merge names it); a folder whose first call
    stopped before any chunk was written does not hold a corrected call to its settings."""
    from hec_jax.loop import sweep
    from hec_jax.runs import write_npz

    config = _tiny_sweep()
    sha = np.full(3, sweep.settings_sha256(config))
    good = tmp_path / "chunks" / "chunk_00000.npz"
    write_npz(good, **{k: np.zeros(3) for k in sweep.CHUNK_KEYS}, settings_sha256=sha)
    assert sweep.chunk_is_complete(good, 3) and not sweep.chunk_is_complete(good, 4)
    damaged = tmp_path / "chunks" / "chunk_00001.npz"
    damaged.write_bytes(good.read_bytes()[:100])
    assert not sweep.chunk_is_complete(damaged)
    unhashed = tmp_path / "unhashed.npz"  # (written before chunks carried their settings)
    write_npz(unhashed, **{k: np.zeros(3) for k in sweep.CHUNK_KEYS})
    assert not sweep.chunk_is_complete(unhashed)
    sweep.check_same_sweep(tmp_path / "chunks", config)
    with pytest.raises(SystemExit, match="damaged chunk files.*chunk_00001"):
        sweep.merge(tmp_path, config)
    fresh = tmp_path / "fresh" / "chunks"
    sweep.check_same_sweep(fresh, _tiny_sweep("--chunk", "3"))  # the first call's settings
    sweep.check_same_sweep(fresh, config)  # no chunk yet: the corrected call is not refused
    write_npz(
        fresh / "chunk_00000.npz",
        **{k: np.zeros(1) for k in sweep.CHUNK_KEYS},
        settings_sha256=sha[:1],
    )
    with pytest.raises(SystemExit, match="other settings"):
        sweep.check_same_sweep(fresh, _tiny_sweep("--chunk", "3"))


def test_a_chunk_of_other_settings_is_never_merged(tmp_path):
    """Two shards started with different arguments before either wrote a chunk: the second
    replaces the first's settings file (nothing computed yet), and the first then writes its
    chunk. The chunk carries its settings' hash: the second's merge and a resume refuse it (no
    metrics, nothing computed), instead of counting it as the second's run."""
    from hec_jax.loop import sweep
    from hec_jax.runs import write_npz

    first, second = _tiny_sweep("--chunk", "3"), _tiny_sweep()
    chunks = tmp_path / "chunks"
    sweep.check_same_sweep(chunks, first)
    sweep.check_same_sweep(chunks, second)  # no chunk yet: the second's settings replace them
    sha_first = np.full(2, sweep.settings_sha256(first))
    assert sha_first[0] != sweep.settings_sha256(second)
    write_npz(
        chunks / "chunk_00000.npz",
        **{k: np.zeros(2) for k in sweep.CHUNK_KEYS},
        settings_sha256=sha_first,
    )
    for call in (lambda: sweep.merge(tmp_path, second), lambda: sweep.run_sweep(second, tmp_path)):
        with pytest.raises(SystemExit, match="other settings than this sweep's.*chunk_00000"):
            call()
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "shard_0").exists()


def test_a_sweep_in_the_other_precision_is_refused(tmp_path):
    """``SweepConfig.float32`` must match ``jax_enable_x64`` (the tests run in float64): else
    the chunks would be computed in one precision and recorded as the other."""
    import dataclasses

    from hec_jax.loop import sweep

    with pytest.raises(ValueError, match="float32 is True but jax_enable_x64 is True"):
        sweep.run_sweep(dataclasses.replace(_tiny_sweep(), float32=True), tmp_path)
    assert not (tmp_path / "chunks").exists()
