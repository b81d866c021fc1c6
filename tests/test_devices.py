"""experiments.devices.OnDevices: runs split over devices, gathered back in order."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.devices import OnDevices, Sharded  # noqa: E402


def _fn(x, scale, pair):
    """Per-run outputs from a batched x (B, 2), an unbatched scale and a (batched, unbatched)
    pair, as the sweep's (keys, switches, conditions) mix them."""
    batched, shared = pair
    return {"y": x * scale + shared[None, :], "z": jnp.sum(x, axis=1) * batched}


def test_runs_come_back_in_order_with_shared_arguments_copied():
    x = np.arange(12.0).reshape(6, 2)
    scale, pair = 3.0, (np.arange(6.0), np.array([1.0, -1.0]))
    device = jax.devices()[0]  # the same device twice: two executables, two threads
    on = OnDevices(_fn, [device, device, device], in_axes=(0, None, (0, None)))
    placed = on.place(x, scale, pair)
    assert [np.shape(p[0]) for p in placed] == [(2, 2)] * 3
    out = on.compile(placed).run(placed)
    want = jax.tree_util.tree_map(np.asarray, _fn(x, scale, pair))
    for k in want:
        np.testing.assert_array_equal(out[k], want[k], err_msg=k)
    again = on(x + 1.0, scale, pair)  # the compiled executables serve new values
    np.testing.assert_array_equal(again["z"], np.asarray(_fn(x + 1.0, scale, pair)["z"]))


def test_one_gspmd_program_has_the_same_interface():
    x = np.arange(12.0).reshape(6, 2)
    scale, pair = 3.0, (np.arange(6.0), np.array([1.0, -1.0]))
    on = Sharded(_fn, jax.devices()[:1], in_axes=(0, None, (0, None)))
    out = on(x, scale, pair)
    want = jax.tree_util.tree_map(np.asarray, _fn(x, scale, pair))
    for k in want:
        np.testing.assert_array_equal(out[k], want[k], err_msg=k)
    with pytest.raises(ValueError, match="differ"):
        on.place(np.zeros((4, 2)), 1.0, (np.zeros(6), np.zeros(2)))


def test_bad_splits_are_refused():
    device = jax.devices()[0]
    with pytest.raises(ValueError, match="0 or None"):
        OnDevices(_fn, [device], in_axes=(1, None, (0, None)))
    on = OnDevices(_fn, [device, device], in_axes=(0, None, (0, None)))
    with pytest.raises(ValueError, match="do not divide"):
        on.place(np.zeros((5, 2)), 1.0, (np.zeros(5), np.zeros(2)))
    with pytest.raises(ValueError, match="differ"):
        on.place(np.zeros((4, 2)), 1.0, (np.zeros(6), np.zeros(2)))
    with pytest.raises(ValueError, match="arguments"):
        on.place(np.zeros((4, 2)), 1.0)
