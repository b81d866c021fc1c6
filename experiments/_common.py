"""Run-folder helpers for the experiment scripts: thin names over :mod:`hec_jax.runs`.

One run folder per invocation: ``config.json`` (seed, package versions, device, command line, and
the experiment's own settings at the top level), ``trajectory.npz`` and PNG plots, all written
atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hec_jax.runs import atomic_write_bytes, save_figure, start_run, write_json, write_npz

__all__ = [
    "atomic_write_bytes",
    "enable_x64",
    "save_figure",
    "save_npz",
    "write_config",
    "write_json",
]

save_npz = write_npz


def write_config(run_dir: str | Path, seed: int, settings: dict[str, Any]) -> Path:
    """Writes ``config.json`` (see :func:`hec_jax.runs.start_run`); returns the run folder."""
    return start_run(run_dir, seed, settings)


def enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
