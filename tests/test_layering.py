"""Imports point one way: geometry, control and nets stand alone; MJX internals in one module;
no library module imports the scripts or edits sys.path (read from the source, not at run time)."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "hec_jax"
SCRIPTS = [Path(__file__).resolve().parents[1] / d for d in ("experiments", "benchmarks")]


def _imports(path: Path) -> set[str]:
    """Every module name a file imports (absolute names; relative imports resolved)."""
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(
                    path.relative_to(PACKAGE.parent).with_suffix("").parts[: -node.level]
                )
                names.add(f"{base}.{node.module}" if node.module else base)
            else:
                names.add(node.module)
                names |= {f"{node.module}.{a.name}" for a in node.names}
    return names


@pytest.mark.parametrize("sub", ["geometry", "control", "nets"])
def test_lower_layers_stand_alone(sub):
    for path in (PACKAGE / sub).rglob("*.py"):
        for name in _imports(path):
            top = name.split(".")[0]
            assert top != "mujoco", f"{path.name} imports {name}"
            if top == "hec_jax":
                assert name.startswith(f"hec_jax.{sub}"), f"{path.name} imports {name}"


def test_world_touches_mjx_internals_in_one_module():
    users = {
        path.name
        for path in PACKAGE.rglob("*.py")
        if "_src" in path.read_text() or "._impl" in path.read_text()
    }
    assert users == {"_mjx_internal.py"}


def test_no_import_runs_back_up():
    """mjx_scene does not import the loop; nothing in the package imports the scripts."""
    for path in PACKAGE.rglob("*.py"):
        for name in _imports(path):
            assert not name.startswith(("experiments", "benchmarks")), f"{path} imports {name}"
            if path.parent.name == "mjx_scene":
                assert not name.startswith(("hec_jax.loop", "hec_jax.control", "hec_jax.nets"))


def test_scripts_do_not_edit_sys_path():
    for folder in SCRIPTS:
        for path in folder.glob("*.py"):
            assert "sys.path" not in path.read_text(), path


def test_headless_rendering_is_the_default_backend():
    """Importing the world sets MUJOCO_GL=egl unless the user chose one (a camera run on a
    machine without a display must not fall back to GLFW and fail), on a Linux with EGL."""
    import ctypes.util
    import os
    import subprocess
    import sys

    code = "import os, hec_jax.loop; print(os.environ.get('MUJOCO_GL'))"
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    expected = "egl" if ctypes.util.find_library("EGL") else "None"
    assert out.stdout.strip() == expected, out.stderr[-2000:]
    env["MUJOCO_GL"] = "glfw"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == "glfw", out.stderr[-2000:]


@pytest.mark.parametrize(
    "system, egl, expected",
    [
        ("Linux", "libEGL.so.1", "egl"),
        ("Linux", None, None),  # no EGL: MuJoCo's own default (GLFW), not a failing import
        ("Darwin", None, None),  # MUJOCO_GL=egl makes ``import mujoco`` raise on macOS
        ("Darwin", "libEGL.dylib", None),
        ("Windows", None, None),
    ],
)
def test_egl_is_set_only_where_mujoco_can_use_it(system, egl, expected):
    from hec_jax import default_gl_backend

    assert default_gl_backend(system, egl) == expected
