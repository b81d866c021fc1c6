"""Run folders: complete or not at all (status, refusal, overwrite, failure, kill), file modes, and
the one video writer (H.264 through imageio-ffmpeg, OpenCV mp4v without)."""

import json
import os
import re
import signal
import subprocess
import sys

import cv2
import numpy as np
import pytest

from hec_jax import runs


def _frames(n=6, h=48, w=64):
    """Frames with a red left half and a blue right half (RGB), brightness rising per frame."""
    out = np.zeros((n, h, w, 3), np.uint8)
    out[:, :, : w // 2, 0] = 200
    out[:, :, w // 2 :, 2] = 200
    out[:, :4] += (np.arange(n, dtype=np.uint8) * 10)[:, None, None, None]
    return out


def _read(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[..., ::-1])  # BGR -> RGB
    cap.release()
    return np.array(frames)


def _check(path, frames):
    back = _read(path)
    assert back.shape == frames.shape
    # lossy, but the colours stay where they were (RGB order kept: red left, blue right)
    left, right = back[:, 8:, : frames.shape[2] // 2 - 4], back[:, 8:, frames.shape[2] // 2 + 4 :]
    assert left[..., 0].mean() > 150 and left[..., 2].mean() < 50
    assert right[..., 2].mean() > 150 and right[..., 0].mean() < 50
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


def test_h264(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    frames = _frames()
    path = tmp_path / "v.mp4"
    assert runs.write_video(path, list(frames), 30.0) == "h264"
    _check(path, frames)
    assert b"avc1" in path.read_bytes()[:4096]  # H.264, index (moov) at the front
    assert path.stat().st_mode & 0o044  # readable by group and others, as every run file


def test_mp4v_without_imageio_ffmpeg(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails
    frames = _frames()
    path = tmp_path / "v.mp4"
    assert runs.write_video(path, iter(frames), 30) == "mp4v"
    _check(path, frames)


def test_odd_size_is_padded(tmp_path):
    frames = _frames(3, 47, 63)
    path = tmp_path / "v.mp4"
    runs.write_video(path, frames, 10.0)
    assert _read(path).shape == (3, 48, 64, 3)


@pytest.mark.parametrize(
    "frames, fps, message",
    [
        ([], 30.0, "no frames"),
        (_frames().astype(np.float32), 30.0, "uint8"),
        ([_frames()[0], _frames(1, 32, 32)[0]], 30.0, "uint8 RGB, got"),
        (_frames()[..., 0], 30.0, "(H, W, 3)"),
        (_frames(), 0.0, "fps"),
    ],
)
def test_bad_input(tmp_path, frames, fps, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        runs.write_video(tmp_path / "v.mp4", frames, fps)
    assert list(tmp_path.iterdir()) == []


def _settings():
    return {"what": "test"}


def test_run_folder_appears_complete_or_not_at_all(tmp_path):
    out = tmp_path / "run"
    with runs.run_folder(out, 0, _settings()) as folder:
        assert not out.exists() and folder.name.startswith(".run.partial-")
        runs.write_json(folder / "metrics.json", {"x": 1})
        config = json.loads((folder / "config.json").read_text())
        assert config["status"] == "running"
    config = json.loads((out / "config.json").read_text())
    assert config["status"] == "complete" and config["what"] == "test"
    assert (out / "metrics.json").stat().st_mode & 0o044  # readable by group and others
    umask = os.umask(0o022)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask  # the folder as a plain mkdir makes it
    # an existing non-empty folder is refused before anything runs; --overwrite replaces it
    with pytest.raises(FileExistsError, match="--overwrite"):
        with runs.run_folder(out, 1, _settings()):
            raise AssertionError("must not run")
    with runs.run_folder(out, 1, _settings(), overwrite=True) as folder:
        runs.write_json(folder / "other.json", {})
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "other.json"]
    assert json.loads((out / "config.json").read_text())["seed"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # nothing left beside it


def test_config_records_the_code_it_ran(tmp_path, monkeypatch):
    # the commit and the dirty flag are git's own answers for the package's checkout
    root = runs.Path(runs.__file__).resolve().parent.parent

    def git(*args):
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)
        return done.stdout.strip() if done.returncode == 0 else None

    with runs.run_folder(tmp_path / "run", 0, _settings()) as folder:
        code = json.loads((folder / "config.json").read_text())["code"]
    if git("rev-parse", "--show-toplevel") == str(root):
        assert code["commit"] == git("rev-parse", "HEAD") and len(code["commit"]) == 40
        assert code["dirty"] == bool(git("status", "--porcelain", "--untracked-files=no"))
    else:  # a copied tree
        assert code["commit"] is None and code["dirty"] is None
    assert code["package_sha256"] == runs.package_digest()

    # no git at all: recorded as unknown, the run goes on
    def no_git(*a, **k):
        raise FileNotFoundError("git")

    monkeypatch.setattr(runs.subprocess, "run", no_git)
    assert runs.code_version() == {
        "commit": None,
        "dirty": None,
        "package_sha256": runs.package_digest(),
    }
    with pytest.raises(ValueError, match="reserved keys"):
        runs.start_run(tmp_path / "other", 0, {"code": 1})


def test_config_records_the_arguments_a_script_parsed_and_no_other_script_s(tmp_path):
    """A script's ``main(argv)`` called from Python: its run folders record ``argv`` (what its
    parser read) as ``parsed_args`` beside the process's ``sys.argv``. A script called inside
    another records its own, and the outer one's later folders the outer's. Outside every
    script's ``main`` a folder records None, also after a parse there."""
    from dataclasses import dataclass

    from hec_jax import cli

    @dataclass(frozen=True)
    class Tiny:
        out: str = "unused"
        overwrite: bool = False
        steps: int = 1

    def config(folder):
        return json.loads((folder / "config.json").read_text())

    @cli.command
    def inner(argv=None):
        a = cli.parse(Tiny(), argv)
        with runs.run_folder(a.out, 0, {"steps": a.steps}) as folder:
            return config(folder)

    @cli.command
    def outer(argv=None):
        a = cli.parse(Tiny(), argv)
        got = [inner(["--out", str(tmp_path / "inner"), "--steps", "7"])]
        with runs.run_folder(a.out, 0, {"steps": a.steps}) as folder:
            return got + [config(folder)]

    args = ["--out", str(tmp_path / "run"), "--steps", "3"]
    first = inner(args)
    assert first["parsed_args"] == args and first["steps"] == 3
    assert first["argv"] == sys.argv
    nested, after = outer(["--out", str(tmp_path / "outer"), "--steps", "5"])
    assert nested["parsed_args"] == ["--out", str(tmp_path / "inner"), "--steps", "7"]
    assert after["parsed_args"] == ["--out", str(tmp_path / "outer"), "--steps", "5"]
    cli.parse(Tiny(), ["--steps", "9"])  # a parse outside any script's main
    with runs.run_folder(tmp_path / "later", 0, {}) as folder:
        assert config(folder)["parsed_args"] is None
    with pytest.raises(ValueError, match="reserved keys"):
        runs.start_run(tmp_path / "other", 0, {"parsed_args": []})


def test_package_digest_names_the_code_not_where_it_lies(tmp_path):
    """:func:`runs.package_digest` against hashlib on a made-up package: the same files in
    another folder give the same digest; a changed byte, a renamed file, bytes moved from one
    file to the next, an added file each give another; ``__pycache__`` is left out."""
    import hashlib

    def package(where, files):
        for rel, data in files.items():
            (where / rel).parent.mkdir(parents=True, exist_ok=True)
            (where / rel).write_bytes(data)
        return where

    files = {"__init__.py": b"x = 1\n", "sub/a.py": b"ab", "sub/b.xml": b"<m/>"}
    one = runs.package_digest(package(tmp_path / "one", files))
    # by hand: sorted relative paths, each length-prefixed path and bytes
    want = hashlib.sha256()
    for rel in sorted(files):
        r, d = rel.encode(), files[rel]
        want.update(len(r).to_bytes(8, "little") + r + len(d).to_bytes(8, "little") + d)
    assert one == want.hexdigest()
    assert runs.package_digest(package(tmp_path / "two", files)) == one
    package(tmp_path / "two", {"__pycache__/a.cpython-311.pyc": b"\0", "sub/__pycache__/b": b""})
    assert runs.package_digest(tmp_path / "two") == one
    others = [
        files | {"sub/a.py": b"ac"},
        {k.replace("a.py", "c.py"): v for k, v in files.items()},
        files | {"sub/a.py": b"a", "sub/b.xml": b"b<m/>"},
        files | {"sub/new.py": b""},
    ]
    digests = {runs.package_digest(package(tmp_path / f"o{i}", f)) for i, f in enumerate(others)}
    assert len(digests) == len(others) and one not in digests


def test_a_failed_run_never_looks_complete(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(ZeroDivisionError):
        with runs.run_folder(out, 0, _settings()) as folder:
            runs.write_json(folder / "half.json", {})
            1 / 0  # noqa: B018
    assert not out.exists()
    (failed,) = tmp_path.glob("run.failed-*")
    config = json.loads((failed / "config.json").read_text())
    assert config["status"] == "failed" and "ZeroDivisionError" in config["error"]


def test_two_failures_in_one_second_keep_both_folders_and_their_errors(tmp_path):
    """The failed folder's name has a resolution of one second; a second failure of the same
    ``out`` in that second gets its own folder (``-2``), and each run's own error propagates."""
    out = tmp_path / "run"
    for i in range(3):
        with pytest.raises(KeyError, match=f"error {i}"):
            with runs.run_folder(out, i, _settings()) as folder:
                runs.write_json(folder / "half.json", {"run": i})
                raise KeyError(f"error {i}")
    failed = sorted(tmp_path.glob("run.failed-*"))
    assert len(failed) == 3 and not out.exists()
    seeds = sorted(json.loads((f / "config.json").read_text())["seed"] for f in failed)
    assert seeds == [0, 1, 2]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no partial left


def test_an_out_made_by_another_run_meanwhile_is_not_replaced(tmp_path):
    """Two runs to the same ``out`` without ``overwrite``: the first to finish takes ``out``;
    the other, finishing later, neither replaces it nor is lost: its folder becomes
    ``<name>.complete-<time>`` and FileExistsError names it."""
    out = tmp_path / "run"
    with pytest.raises(FileExistsError, match="appeared while this run ran") as err:
        with runs.run_folder(out, 0, _settings()) as folder_a:
            runs.write_json(folder_a / "metrics.json", {"run": "A"})
            with runs.run_folder(out, 1, _settings()) as folder_b:  # B starts after A, ends first
                runs.write_json(folder_b / "metrics.json", {"run": "B"})
            assert json.loads((out / "metrics.json").read_text()) == {"run": "B"}
    assert json.loads((out / "metrics.json").read_text()) == {"run": "B"}  # B's, untouched
    (kept,) = tmp_path.glob("run.complete-*")
    assert str(kept) in str(err.value)
    assert json.loads((kept / "metrics.json").read_text()) == {"run": "A"}
    assert json.loads((kept / "config.json").read_text())["status"] == "complete"
    # with overwrite the later run replaces the earlier one, as before
    with runs.run_folder(out, 2, _settings(), overwrite=True) as folder:
        runs.write_json(folder / "metrics.json", {"run": "C"})
    assert json.loads((out / "metrics.json").read_text()) == {"run": "C"}


def test_a_killed_run_leaves_no_run_folder(tmp_path):
    """A process killed (SIGKILL) while it writes leaves only the hidden partial folder; an
    earlier complete run in the same place is untouched."""
    out = tmp_path / "run"
    with runs.run_folder(out, 0, _settings()) as folder:
        runs.write_json(folder / "metrics.json", {"run": "first"})
    script = (
        "import time, sys\n"
        "from hec_jax import runs\n"
        "with runs.run_folder(sys.argv[1], 0, {}, overwrite=True) as f:\n"
        "    runs.write_json(f / 'metrics.json', {'run': 'second'})\n"
        "    print('writing', flush=True)\n"
        "    time.sleep(60)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(out)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "writing"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert json.loads((out / "metrics.json").read_text()) == {"run": "first"}
    assert json.loads((out / "config.json").read_text())["status"] == "complete"
    partial = [p for p in tmp_path.iterdir() if p.name.startswith(".run.partial-")]
    assert len(partial) == 1
    assert json.loads((partial[0] / "config.json").read_text())["status"] == "running"


def test_device_records_the_processor(tmp_path):
    # the processor's model name, as the kernel reports it (timings compare only on the same)
    model = None
    try:
        lines = runs.Path("/proc/cpuinfo").read_text().splitlines()
        model = next(ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    with runs.run_folder(tmp_path / "run", 0, _settings()) as folder:
        device = json.loads((folder / "config.json").read_text())["device"]
    if model is not None:
        assert device["cpu_model"] == model
    assert device["cpu_count"] >= 1
    # family, model and stepping: what tells apart two processors of one model name
    try:
        text = runs.Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    numbers = re.findall(r"^(cpu family|model|stepping)\s*:\s*(\S+)", text, re.M)[:3]
    if len(numbers) == 3:
        want = dict(numbers)
        assert device["cpu_id"] == (
            f"family {want['cpu family']} model {want['model']} stepping {want['stepping']}"
        )


def test_device_records_the_xla_flags(tmp_path, monkeypatch):
    # XLA_FLAGS decide on a GPU whether two runs give the same numbers: recorded, None unset
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_deterministic_ops=true")
    assert runs.device_description()["xla_flags"] == "--xla_gpu_deterministic_ops=true"
    monkeypatch.delenv("XLA_FLAGS")
    with runs.run_folder(tmp_path / "run", 0, _settings()) as folder:
        assert json.loads((folder / "config.json").read_text())["device"]["xla_flags"] is None


def test_the_umask_is_read_as_set():
    """Files and folders get the mode a plain open/mkdir would give (``0o666 & ~umask``), the
    umask read without being changed where Linux gives it."""
    old = os.umask(0o027)
    try:
        assert runs._umask() == 0o027
        os.umask(0o002)
        assert runs._umask() == 0o002
    finally:
        os.umask(old)
