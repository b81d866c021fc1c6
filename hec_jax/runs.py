"""Run folders: one folder per experiment or benchmark run, written atomically.

Every run writes ``config.json`` (seed, command line, package versions, git commit and a digest
of the package's code, device, its own settings), then its metrics, plots (PNG) and videos
(MP4), into the folder given by ``--out``. Files are written to a temporary name and moved
into place, so an interrupted run never leaves a half-written file.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

_PACKAGES = (
    "jax",
    "jaxlib",
    "mujoco",
    "mujoco-mjx",
    "numpy",
    "flax",
    "optax",
    "opencv-python-headless",
    "imageio-ffmpeg",
)


def package_versions() -> dict[str, str]:
    """Installed versions of the packages results depend on."""
    out = {}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def package_digest(root: str | os.PathLike | None = None) -> str:
    """SHA-256 of a package's source: every file under ``root`` (default: this ``hec_jax``) but
    ``__pycache__``, in sorted order, each as its relative path and its bytes.

    The same code gives the same digest wherever it runs, git or not; so a run made from a copied
    tree (a GPU machine, whose git base may be older than the code it ran) can be matched to a
    commit by computing the digest of that commit's ``hec_jax/``.
    """
    root = Path(__file__).resolve().parent if root is None else Path(root)
    digest = hashlib.sha256()
    files = sorted(
        p for p in root.rglob("*") if p.is_file() and "__pycache__" not in p.relative_to(root).parts
    )
    for path in files:
        rel = path.relative_to(root).as_posix().encode()
        data = path.read_bytes()
        digest.update(len(rel).to_bytes(8, "little") + rel + len(data).to_bytes(8, "little"))
        digest.update(data)
    return digest.hexdigest()


def code_version() -> dict[str, Any]:
    """The source tree the run imported ``hec_jax`` from: ``commit`` (git HEAD, 40 hex digits) and
    ``dirty`` (tracked files changed since it), both None where that tree is not a git checkout
    or git is not installed (e.g. a copied tree on a GPU machine); and ``package_sha256``
    (:func:`package_digest`), which names the package's code whatever git says.
    """
    root = Path(__file__).resolve().parent.parent
    digest = package_digest()

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(
                ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "--verify", "HEAD")
    if commit is None or git("rev-parse", "--show-toplevel") != str(root):
        # not this package's own checkout
        return {"commit": None, "dirty": None, "package_sha256": digest}
    status = git("status", "--porcelain", "--untracked-files=no")
    dirty = None if status is None else bool(status)
    return {"commit": commit, "dirty": dirty, "package_sha256": digest}


def cpu_model() -> str | None:
    """The processor's model name (Linux: ``/proc/cpuinfo``; else ``platform.processor()``), or
    None where neither says: two machines of one kind may have different processors, and
    timings are comparable only on the same.
    """
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def cpu_id() -> str | None:
    """The processor's family, model and stepping numbers from Linux's ``/proc/cpuinfo`` (e.g.
    ``"family 25 model 17 stepping 1"``), or None where it does not say. The model name can be
    the same for different processors ("AMD EPYC" for Zen 3 and Zen 4 guests), and XLA's CPU
    code, with it the eye's tracks and timings, differs between them (docs/testing.md).
    """
    fields = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the first processor's block only
                key, _, value = line.partition(":")
                fields[key.strip().lower()] = value.strip()
    except OSError:
        return None
    parts = [(n, fields.get(k)) for n, k in (("family", "cpu family"), ("model", "model"))]
    parts.append(("stepping", fields.get("stepping")))
    if any(v is None for _, v in parts):
        return None
    return " ".join(f"{n} {v}" for n, v in parts)


def device_description() -> dict[str, Any]:
    """The machine and JAX backend the run used, and the environment's ``XLA_FLAGS`` (None where
    unset): on a GPU they decide whether two runs of the same code give the same numbers
    (``--xla_gpu_deterministic_ops``, docs/experiments.md).
    """
    import jax

    return {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpu_model": cpu_model(),
        "cpu_id": cpu_id(),
        "cpu_count": os.cpu_count(),
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "xla_flags": os.environ.get("XLA_FLAGS"),
    }


def _default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "__array__"):  # JAX arrays
        return np.asarray(obj).tolist()
    raise TypeError(f"not JSON serialisable: {type(obj)}")


_MAX_NULL_REASONS = 100  # paths listed in ``non_finite_as_null`` (the count is always exact)


def json_safe(obj: Any) -> tuple[Any, dict[str, str]]:
    """``obj`` with every value JSON can hold (NumPy and JAX arrays as lists) and every non-finite
    number (NaN, inf: not JSON) as None, and ``{path: "nan" | "inf" | "-inf"}`` of what became
    None (paths like ``learned.peak_force.mean`` or ``per_run.3.peak_plain``).
    """
    nulls: dict[str, str] = {}

    def walk(x, path):
        if isinstance(x, dict):
            return {k: walk(v, f"{path}.{k}" if path else str(k)) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [walk(v, f"{path}.{i}" if path else str(i)) for i, v in enumerate(x)]
        if isinstance(x, (bool, str, int)) or x is None:
            return x
        if isinstance(x, float):
            if not np.isfinite(x):
                nulls[path] = "nan" if np.isnan(x) else ("inf" if x > 0 else "-inf")
                return None
            return x
        return walk(_default(x), path)

    return walk(obj, ""), nulls


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    _publish(path, write, suffix=".tmp")


def _publish(path: Path, write, suffix: str) -> None:
    """``write(tmp)`` a temporary file beside ``path``, sync it, make it group-readable (mkstemp
    makes 0600; results are shared) and rename it to ``path``; on any failure remove it.
    """
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _umask() -> int:
    """The process's umask, read without changing it where Linux says it (``/proc/self/status``):
    setting and restoring it would briefly give another thread's new files the wrong mode.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Atomic JSON write (NumPy and JAX arrays and scalars allowed); strict JSON.

    JSON has no NaN or infinity: a non-finite number is written as ``null`` and, when ``obj`` is
    a dict, the top-level ``non_finite_as_null`` says where and what it was (``{"count": n,
    "paths": {"learned.peak_force.mean": "nan", ...}}``, the first 100 paths; a NaN is e.g. a
    diverged run or a mean over nothing).
    """
    safe, nulls = json_safe(obj)
    if nulls and isinstance(safe, dict):
        listed = dict(itertools.islice(nulls.items(), _MAX_NULL_REASONS))
        safe["non_finite_as_null"] = {"count": len(nulls), "paths": listed}
    text = json.dumps(safe, indent=2, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())


def write_text(path: str | os.PathLike, text: str) -> None:
    """Writes ``text`` (UTF-8) atomically."""
    atomic_write_bytes(path, text.encode())


def write_npz(path: str | os.PathLike, **arrays) -> None:
    """Atomic, compressed ``np.savez_compressed`` of named arrays (``np.load`` reads it)."""
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    atomic_write_bytes(path, buf.getvalue())


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> None:
    """Atomic PNG of a matplotlib figure."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def _even_frames(frames, shape):
    """Checks each RGB uint8 frame against ``shape`` and pads it to even height and width by
    repeating its last row/column (H.264 with 4:2:0 chroma needs even sizes).
    """
    for frame in frames:
        f = np.asarray(frame)
        if f.dtype != np.uint8 or f.shape != shape:
            raise ValueError(f"frames must be {shape} uint8 RGB, got {f.shape} {f.dtype}")
        if shape[0] % 2 or shape[1] % 2:
            f = np.pad(f, ((0, shape[0] % 2), (0, shape[1] % 2), (0, 0)), mode="edge")
        yield np.ascontiguousarray(f)


def _write_h264(path: str, frames, size: tuple[int, int], fps: float) -> None:
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(
        path,
        size,
        fps=fps,
        macro_block_size=1,  # sizes are even already; no rescaling
        ffmpeg_log_level="error",
        output_params=["-movflags", "+faststart"],  # index first: plays while loading
    )
    with warnings.catch_warnings():
        # JAX warns at any fork; the ffmpeg process is started by fork + exec at once (Popen)
        warnings.filterwarnings("ignore", "os.fork()", RuntimeWarning)
        writer.send(None)
    try:
        for f in frames:
            writer.send(f)
    finally:
        writer.close()


def _write_mp4v(path: str, frames, size: tuple[int, int], fps: float) -> None:
    import cv2

    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    try:
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV cannot write an mp4v video to {path}")
        for f in frames:
            writer.write(np.ascontiguousarray(f[..., ::-1]))  # OpenCV takes BGR
    finally:
        writer.release()


def write_video(path: str | os.PathLike, frames, fps: float) -> str:
    """MP4 of ``frames`` at ``fps``, written next to its final name and renamed (atomic).

    H.264 (yuv420p, index first: plays in a browser) through the ffmpeg binary that the
    ``imageio-ffmpeg`` package ships, when it is installed; otherwise OpenCV's MPEG-4 Part 2
    (``mp4v``), which most browsers do not play. Frames of odd height or width are padded by one
    row or column (a copy of the last one).

    Args:
        path: the ``.mp4`` file.
        frames: an iterable (a list, an array (T, H, W, 3), a generator) of RGB uint8 frames
            (H, W, 3), all of one shape; streamed, not stacked.
        fps: frames per second.

    Returns:
        The codec used: ``"h264"`` or ``"mp4v"``.

    Raises:
        ValueError: no frames, a frame that is not (H, W, 3) uint8 or not of the first one's
            shape, or ``fps`` not positive.
        RuntimeError: the writer could not open the file.
    """
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    frames = iter(frames)
    head = next(frames, None)
    if head is None:
        raise ValueError("no frames to write")
    shape = np.shape(head)
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"frames must be (H, W, 3) uint8 RGB, got {shape}")
    size = (shape[1] + shape[1] % 2, shape[0] + shape[0] % 2)  # (width, height), even
    try:
        import imageio_ffmpeg  # noqa: F401

        write, codec = _write_h264, "h264"
    except ImportError:
        write, codec = _write_mp4v, "mp4v"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stream = _even_frames(itertools.chain([head], frames), shape)
    _publish(path, lambda tmp: write(tmp, stream, size, float(fps)), suffix=".tmp.mp4")
    return codec


# The arguments the running script's parser read in this thread (``hec_jax.cli.parse``): a
# script's ``main(argv)`` called from Python parses ``argv``, not the process's ``sys.argv``.
# ``.args`` the arguments, ``.depth`` how many ``script_arguments`` scopes are open.
_parsed = threading.local()


def note_parsed_args(args: list[str]) -> None:
    """Remember ``args``, the arguments a script's parser just read (called by
    :func:`hec_jax.cli.parse`), for the run folders the script starts (inside
    :func:`script_arguments`; outside one they are not recorded).
    """
    _parsed.args = [str(a) for a in args]


@contextlib.contextmanager
def script_arguments():
    """The scope of one script's ``main`` (:func:`hec_jax.cli.command`): the arguments its
    parser notes are what its run folders record as ``parsed_args``; a script's ``main`` called
    inside another's notes its own for its folders, and the outer script's are back when it
    returns. Outside every scope a run folder records None.
    """
    saved = getattr(_parsed, "args", None), getattr(_parsed, "depth", 0)
    if saved[1] == 0:  # the outermost script: nothing parsed outside it is its own
        _parsed.args = None
    _parsed.depth = saved[1] + 1
    try:
        yield
    finally:
        _parsed.args, _parsed.depth = saved


_RESERVED_KEYS = frozenset(
    {"seed", "command", "argv", "parsed_args", "versions", "code", "device", "started_utc"}
)


def _check_settings(settings: dict[str, Any]) -> None:
    reserved = _RESERVED_KEYS & set(settings)
    if reserved:
        raise ValueError(f"settings may not use the reserved keys {sorted(reserved)}")


def start_run(out: str | os.PathLike, seed: int, settings: dict[str, Any]) -> Path:
    """Create the run folder and write its ``config.json``; returns the folder.

    ``config.json`` holds ``seed``, ``command`` and ``argv`` (the process's), ``parsed_args``
    (the arguments the running script's parser read, :func:`note_parsed_args`; they differ from
    ``argv[1:]`` where a script's ``main(argv)`` was called from Python; None outside a script's
    ``main`` (:func:`script_arguments`) or before its parser ran, and in another thread),
    ``versions``, ``code`` (git commit and the package's digest, :func:`code_version`),
    ``device`` and, at the top level beside them, the run's own ``settings`` (so e.g. ``m_e``
    is ``config["m_e"]``).
    """
    _check_settings(settings)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(
        folder / "config.json",
        {
            "seed": int(seed),
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "command": " ".join([sys.executable, *sys.argv]),
            "argv": list(sys.argv),
            "parsed_args": getattr(_parsed, "args", None) if getattr(_parsed, "depth", 0) else None,
            "versions": package_versions(),
            "code": code_version(),
            "device": device_description(),
            **settings,
        },
    )
    return folder


def _set_status(folder: Path, status: str, error: str | None = None) -> None:
    try:
        config = json.loads((folder / "config.json").read_text())
    except FileNotFoundError:  # failed before start_run had written it
        config = {}
    config.update(status=status, finished_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    if error is not None:
        config["error"] = error
    write_json(folder / "config.json", config)


def check_out(out: str | os.PathLike, overwrite: bool = False) -> None:
    """Refuses a run folder ``out`` that exists and is not empty (unless ``overwrite``).

    Raises:
        FileExistsError: with a one-line message naming ``--out`` and ``--overwrite``.
    """
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise FileExistsError(
            f"{out} exists and is not empty: choose another --out, or pass --overwrite"
        )


# The run folders open in this process (``run_folder`` blocks), innermost last, for
# ``fail_active_run`` (a signal handler at the command-line boundary, ``hec_jax.cli``). The lock
# makes a run's last steps (status, renames) and a failure from another thread exclusive.
_ACTIVE: list[dict[str, Path]] = []
_LOCK = threading.RLock()


def _move_aside(partial: Path, out: Path, kind: str) -> Path:
    """Renames ``partial`` to a new sibling ``<name>.<kind>-<UTC time>`` of ``out`` (``-2``,
    ``-3``, ... appended while that name is taken: two runs ending in the same second keep both
    folders) and returns it.
    """
    base = f"{out.name}.{kind}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
    for n in itertools.count(1):
        target = out.with_name(base if n == 1 else f"{base}-{n}")
        try:
            target.mkdir()  # claims the name (atomic); the folder then takes its place
        except FileExistsError:
            continue
        os.replace(partial, target)
        return target
    raise AssertionError("unreachable")


def _fail(run: dict[str, Path], error: str) -> Path:
    """Marks the partial folder of ``run`` failed and renames it ``<name>.failed-<UTC time>``."""
    partial, out = run["partial"], run["out"]
    for tmp in partial.glob(".*.tmp*"):  # a file being written when the run stopped
        tmp.unlink(missing_ok=True)
    _set_status(partial, "failed", error)
    return _move_aside(partial, out, "failed")


# how long a signal's handler waits for a run folder's start (config.json: the JAX backend, git)
# before it gives up on the folder, which then stays partial as a killed run's does
FAIL_WAIT_S = 10.0


def fail_active_run(error: str, wait_s: float = FAIL_WAIT_S) -> Path | None:
    """Ends the innermost open :func:`run_folder` as failed (``error`` recorded in its
    ``config.json``) and returns the failed folder; None when no run folder is open or its run
    has just completed, or when a run's start or last steps hold the folder longer than
    ``wait_s`` (a stuck JAX backend must not keep Ctrl-C from ending the process). For a
    handler that then ends the process (``os._exit``), e.g. on Ctrl-C.
    """
    if not _LOCK.acquire(timeout=wait_s):
        return None
    try:
        if not _ACTIVE or not _ACTIVE[-1]["partial"].exists():
            return None
        return _fail(_ACTIVE.pop(), error)
    finally:
        _LOCK.release()


def _fail_noting(run: dict[str, Path], e: BaseException) -> None:
    """``_fail`` for a run that raised ``e``, said on stderr; if the folder cannot be marked
    failed either (a full disk), that is noted on ``e``, which the caller re-raises.
    """
    try:
        failed = _fail(run, f"{type(e).__name__}: {e}")
    except Exception as err:  # noqa: BLE001 (noted on the error the caller raises)
        e.add_note(f"its run folder {run['partial']} could not be marked failed: {err!r}")
        return
    print(f"run failed; what it wrote is in {failed}", file=sys.stderr)


@contextlib.contextmanager
def run_folder(
    out: str | os.PathLike, seed: int, settings: dict[str, Any], overwrite: bool = False
):
    """A run folder that appears complete, or not at all (a context manager yielding the folder
    to write into).

    The run writes into a new hidden sibling ``.<name>.partial-<pid>-<random>`` whose ``config.json`` says
    ``"status": "running"``; when the block ends normally the status becomes ``complete`` and
    the folder is renamed to ``out`` (replacing an old one only with ``overwrite``; if another
    run made ``out`` meanwhile, this one becomes ``<name>.complete-<UTC time>`` and
    FileExistsError says so). If the block
    raises (Ctrl-C included) the status becomes ``failed`` with the error, and the folder is
    renamed to ``<name>.failed-<UTC time>``; so does :func:`fail_active_run` (the scripts'
    SIGINT/SIGTERM handler); a killed process leaves only the hidden partial folder. Either way
    ``out`` never holds a mix of two runs or a run that did not finish.

    Raises:
        FileExistsError: ``out`` exists, is not empty and ``overwrite`` is False (checked
            before anything is computed, and again at the end: see above).
    """
    out = Path(out)
    check_out(out, overwrite)
    _check_settings(settings)
    out.parent.mkdir(parents=True, exist_ok=True)
    with _LOCK:
        # Open from the moment the folder exists: a signal while config.json is being written
        # (versions, git, the JAX backend: seconds on a busy machine) waits for the lock, then
        # fails the folder, rather than finding no open run and leaving it partial.
        # A new name for every run, even two in one process (a killed run's folder stays).
        partial = Path(
            tempfile.mkdtemp(prefix=f".{out.name}.partial-{os.getpid()}-", dir=out.parent)
        )
        run = {"partial": partial, "out": out}
        _ACTIVE.append(run)
        try:
            os.chmod(partial, 0o777 & ~_umask())  # (mkdtemp makes it private) as mkdir would
            start_run(partial, seed, dict(settings, status="running"))
        except BaseException as e:
            _ACTIVE.remove(run)
            _fail_noting(run, e)
            raise
    try:
        yield partial
    except BaseException as e:
        with _LOCK:
            if run in _ACTIVE:  # else a signal handler has failed it already
                _ACTIVE.remove(run)
                _fail_noting(run, e)
        raise
    with _LOCK:  # the last steps, not to be cut by fail_active_run from another thread
        if run not in _ACTIVE:
            raise RuntimeError(f"the run was ended as failed while it ran: {out}")
        _ACTIVE.remove(run)
        _set_status(partial, "complete")
        if not overwrite and out.exists() and (not out.is_dir() or any(out.iterdir())):
            # another run made ``out`` while this one ran: neither replaces the other
            kept = _move_aside(partial, out, "complete")
            raise FileExistsError(
                f"{out} appeared while this run ran and --overwrite was not given: it is left"
                f" as it is, and this run's complete results are in {kept}"
            )
        if out.exists():
            old = out.with_name(f".{out.name}.replaced-{os.getpid()}")
            os.replace(out, old)
            os.replace(partial, out)
            shutil.rmtree(old) if old.is_dir() else old.unlink()
        else:
            os.replace(partial, out)


def enable_compile_cache() -> None:
    """Use JAX's persistent compilation cache in the folder named by ``HEC_JAX_CACHE``, if set."""
    folder = os.environ.get("HEC_JAX_CACHE")
    if folder:
        import jax

        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
