"""A sweep across hosts as a scheduler runs it: ``scripts/local_sweep.sh`` emulates the SLURM job
array of ``scripts/slurm_sweep.sh`` (N shard processes at once into one folder, then the merge)."""

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
    "--seeds", "1", "--swings", "2", "--swing-s", "0.7", "--chunk", "1",
]  # fmt: skip


def _env():
    env = dict(os.environ, PYTHON=sys.executable)
    env.setdefault("HEC_JAX_CACHE", str(ROOT / ".jax_cache"))
    return env


def _run(cmd, **kw):
    return subprocess.run(
        cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=600, **kw
    )


def _merge_only(out, *args):
    return _run([sys.executable, "experiments/sweep.py", "--out", str(out), "--merge-only", *args])


def _assert_refused(proc):
    """Exit code 2 and a one-line ``error:`` message naming the differing setting."""
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "error:" in lines[0] and "other settings" in lines[0], lines
    assert "'seeds': (1, 2)" in lines[0]


def _with_seeds(n):
    """TINY with another seed count (another sweep)."""
    i = TINY.index("--seeds")
    return [*TINY[: i + 1], str(n), *TINY[i + 2 :]]


def _assert_same(a, b, where="metrics"):
    """Same JSON structure; numbers equal to 1e-12 (relative)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and not isinstance(a, bool):
        np.testing.assert_allclose(a, b, rtol=1e-12, err_msg=where)
    else:
        assert a == b, where


def test_local_array_script_arguments():
    """The script's usage check and the commands it runs (DRY_RUN=1): N shards, then the merge,
    each with the same sweep arguments."""
    bad = _run(["bash", "scripts/local_sweep.sh", "0", "runs/x"])
    assert bad.returncode == 2 and "usage:" in bad.stderr
    dry = subprocess.run(
        ["bash", "scripts/local_sweep.sh", "3", "out/s", "--seeds", "2"],
        cwd=ROOT, env={**_env(), "DRY_RUN": "1"}, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert dry.returncode == 0, dry.stderr
    lines = dry.stdout.strip().splitlines()
    py = sys.executable
    assert lines == [
        *(f"{py} experiments/sweep.py --out out/s --shard-index {i} --num-shards 3 --seeds 2"
          for i in range(3)),
        f"{py} experiments/sweep.py --out out/s --merge-only --seeds 2",
    ]  # fmt: skip
    text = (ROOT / "scripts" / "slurm_sweep.sh").read_text()
    assert "#SBATCH --array=" in text


def test_slurm_scripts_with_a_fake_sbatch(tmp_path):
    """slurm_submit.sh submits the array and a merge after it (afterok) with the same flags; an
    array task runs its shard, the merge job --merge-only (PYTHON=echo: the commands only)."""
    log = tmp_path / "sbatch.log"
    fake = tmp_path / "bin" / "sbatch"
    fake.parent.mkdir()
    fake.write_text(
        '#!/bin/bash\necho "$*" >> "$SBATCH_LOG"\necho "$((41 + $(wc -l < "$SBATCH_LOG")));c"\n'
    )
    fake.chmod(0o755)
    env = {**_env(), "PATH": f"{fake.parent}:{os.environ['PATH']}", "SBATCH_LOG": str(log),
           "SWEEP_DIR": "/shared/s"}  # fmt: skip
    flags = ["--seeds", "2", "--rod-lengths", "0.5", "0.6"]
    sub = subprocess.run(
        ["bash", "scripts/slurm_submit.sh", "4", *flags],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert sub.returncode == 0, sub.stderr
    here, tail = ROOT / "scripts", " ".join(flags)
    assert log.read_text().splitlines() == [
        f"--parsable --array=0-3 --export=ALL {here}/slurm_sweep.sh {tail}",
        f"--parsable --dependency=afterok:42 --export=ALL {here}/slurm_merge.sh {tail}",
    ]
    task = {**env, "PYTHON": "echo", "SLURM_ARRAY_TASK_ID": "3", "SLURM_ARRAY_TASK_COUNT": "4",
            "SLURM_SUBMIT_DIR": str(ROOT)}  # fmt: skip
    for script, expected in [
        ("slurm_sweep.sh", "--shard-index 3 --num-shards 4"),
        ("slurm_merge.sh", "--merge-only"),
    ]:
        job = subprocess.run(
            ["bash", str(ROOT / "scripts" / script), *flags],
            cwd=tmp_path, env=task, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert job.returncode == 0, job.stderr
        assert job.stdout.strip() == f"experiments/sweep.py --out /shared/s {expected} {tail}"
    no_dir = subprocess.run(
        ["bash", "scripts/slurm_submit.sh", "4"], cwd=ROOT, env={**env, "SWEEP_DIR": ""},
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert no_dir.returncode != 0 and "SWEEP_DIR" in no_dir.stderr


def test_merge_of_other_settings_is_refused(tmp_path):
    """A folder whose chunks were computed with one seed: merging it as a two-seed sweep is
    refused (exit code 2, one line) and leaves no metrics."""
    from hec_jax.cli import parse
    from hec_jax.loop.cli import SweepRun

    chunks = tmp_path / "chunks"
    chunks.mkdir()
    settings = parse(SweepRun(), TINY).sweep.settings()
    (chunks / "sweep_settings.json").write_text(json.dumps(settings))
    (chunks / "chunk_00000.npz").write_bytes(b"")  # any chunk: the settings are kept
    proc = _merge_only(tmp_path, *_with_seeds(2))
    _assert_refused(proc)
    assert not (tmp_path / "metrics.json").exists()


@pytest.mark.slow
def test_shard_processes_in_parallel_then_merge_match_one_process(tmp_path):
    """Two shard processes at once (scripts/local_sweep.sh 2), then --merge-only: every chunk
    once, the merged metrics those of one process computing the whole sweep; a merge with
    another seed count is refused."""
    sharded, single = tmp_path / "sharded", tmp_path / "single"
    proc = _run(["bash", "scripts/local_sweep.sh", "2", str(sharded), *TINY])
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-3000:]
    assert "merged 2/2 runs" in proc.stdout
    for i in (0, 1):  # each shard computed its own chunk only
        timing = json.loads((sharded / f"shard_{i}" / "timing.json").read_text())
        assert timing["chunks_run"] == 1, (sharded / "logs" / f"shard_{i}.log").read_text()
    files = sorted(p.name for p in (sharded / "chunks").glob("chunk_*.npz"))
    assert files == ["chunk_00000.npz", "chunk_00001.npz"]
    merged = json.loads((sharded / "metrics.json").read_text())
    assert merged["runs_done"] == merged["runs_total"] == 2
    assert merged["chunks_done"] == merged["chunks_total"] == 2

    one = _run([sys.executable, "experiments/sweep.py", "--out", str(single), *TINY])
    assert one.returncode == 0, one.stderr[-3000:]
    reference = json.loads((single / "metrics.json").read_text())
    _assert_same(merged, reference)

    before = (sharded / "metrics.json").read_text()
    _assert_refused(_merge_only(sharded, *_with_seeds(2)))
    assert (sharded / "metrics.json").read_text() == before  # untouched
