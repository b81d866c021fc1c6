"""hec_jax: hand-eye coordination for flexible impedance control, in JAX/MJX.

Importing the package makes headless rendering (EGL) MuJoCo's default backend on Linux, where
an EGL library is installed, unless the user chose one (``MUJOCO_GL``): MuJoCo reads it when it
is first imported, and this library runs mostly without a display (CI, GPU hosts); import
``hec_jax`` before ``mujoco`` for it to apply. Elsewhere (macOS, Windows, a Linux without EGL)
nothing is set and MuJoCo keeps its own default: ``MUJOCO_GL=egl`` there would make
``import mujoco`` fail.
"""

import ctypes.util
import os
import platform


def default_gl_backend(system: str, egl_library: str | None) -> str | None:
    """The ``MUJOCO_GL`` to set when the user set none: "egl" on Linux (``system`` as
    ``platform.system()``) with an EGL library found (``egl_library``, as
    ``ctypes.util.find_library("EGL")``), else None (leave MuJoCo's default).
    """
    return "egl" if system == "Linux" and egl_library else None


if "MUJOCO_GL" not in os.environ:  # (the library search runs ldconfig: only when needed)
    _backend = default_gl_backend(platform.system(), ctypes.util.find_library("EGL"))
    if _backend is not None:
        os.environ["MUJOCO_GL"] = _backend
