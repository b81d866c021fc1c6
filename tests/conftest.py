"""Strict JAX configuration shared by every test.

* float64 available (float32 tests pass float32 arrays explicitly),
* rank promotion raises (no silent broadcasting),
* persistent compilation cache, so repeated CI runs and test processes reuse compiles.
"""

import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402

_CACHE_DIR = Path(
    os.environ.get("HEC_JAX_CACHE", Path(__file__).resolve().parents[1] / ".jax_cache")
)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_compilation_cache_dir", str(_CACHE_DIR))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

# Hypothesis: in CI (CI=true) draw the same examples every run, so a red build is reproducible.
from hypothesis import settings as _hypothesis_settings  # noqa: E402

_hypothesis_settings.register_profile("ci", derandomize=True, deadline=None)
if os.environ.get("CI"):
    _hypothesis_settings.load_profile("ci")

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _clear_jax_caches():
    """With ``HEC_TEST_CLEAR_JAX_CACHES=1``, drop JAX's in-memory executables and traces after
    each test module (the persistent cache on disk stays). Off by default: the modules that share
    the eye's tracker then trace and load it once per worker process, not once per module. It was
    on for a jaxlib segfault that no longer reproduces (docs/testing.md, "JAX's caches kept
    across test modules").
    """
    yield
    if os.environ.get("HEC_TEST_CLEAR_JAX_CACHES") == "1":
        jax.clear_caches()
