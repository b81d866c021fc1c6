"""Imports ``mujoco.mjx`` once, without the two lines it prints when the optional MuJoCo Warp
backend is simply not installed ("Failed to import warp: No module named 'warp'", on every
import). Any other output of that import (e.g. an installed warp that fails to load) is printed
as usual. Imported first by ``hec_jax.mjx_scene``.
"""

import contextlib
import io


def import_mjx_quietly() -> None:
    """Imports ``mujoco.mjx`` with the warp-not-installed lines filtered out of its output."""
    captured = io.StringIO()
    with contextlib.redirect_stdout(captured):
        from mujoco import mjx  # noqa: F401
    for line in captured.getvalue().splitlines():
        absent = "No module named 'warp'" in line
        if not (absent and line.startswith(("Failed to import warp", "Failed to import mujoco"))):
            print(line)


import_mjx_quietly()
