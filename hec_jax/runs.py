"""Run folders: one folder per experiment or benchmark run, written atomically.

Every run writes ``config.json`` (seed, command line, package versions, device, its own settings),
then its metrics and plots, into the folder given by ``--out``. Files are written to a temporary
name and moved into place, so an interrupted run never leaves a half-written file.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
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


def device_description() -> dict[str, Any]:
    """The machine and JAX backend the run used."""
    import jax

    return {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
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


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Atomic JSON write (NumPy arrays and scalars allowed)."""
    atomic_write_bytes(path, (json.dumps(obj, indent=2, default=_default) + "\n").encode())


def write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_npz(path: str | os.PathLike, **arrays) -> None:
    """Atomic ``np.savez`` of named arrays."""
    import io

    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    atomic_write_bytes(path, buf.getvalue())


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> None:
    """Atomic PNG of a matplotlib figure."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def start_run(out: str | os.PathLike, seed: int, settings: dict[str, Any]) -> Path:
    """Create the run folder and write its ``config.json``; returns the folder.

    ``config.json`` holds ``seed``, ``command``, ``argv``, ``versions``, ``device`` and, at the top
    level beside them, the run's own ``settings`` (so e.g. ``m_e`` is ``config["m_e"]``).
    """
    reserved = {"seed", "command", "argv", "versions", "device"} & set(settings)
    if reserved:
        raise ValueError(f"settings may not use the reserved keys {sorted(reserved)}")
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(
        folder / "config.json",
        {
            "seed": int(seed),
            "command": " ".join([sys.executable, *sys.argv]),
            "argv": list(sys.argv),
            "versions": package_versions(),
            "device": device_description(),
            **settings,
        },
    )
    return folder


def enable_compile_cache() -> None:
    """Use JAX's persistent compilation cache in the folder named by ``HEC_JAX_CACHE``, if set."""
    folder = os.environ.get("HEC_JAX_CACHE")
    if folder:
        import jax

        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
