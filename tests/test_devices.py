"""hec_jax.loop.devices.OnDevices: runs split over devices, gathered back in order."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

from hec_jax.loop.devices import OnDevices, Sharded  # noqa: E402


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


TWO_DEVICES = """
import sys, threading
from typing import NamedTuple

import jax
import numpy as np

from hec_jax.loop.devices import OnDevices


class Switch(NamedTuple):  # as the sweep's switches: batched leaves and an unbatched field
    gain: object
    flag: object
    eye: object


traces = []
both_running = threading.Barrier(2)


def wait_for_the_other(x):  # returns only while the other device runs its executable too
    both_running.wait(timeout=30)
    return x


def fn(x, sw, shared):
    traces.append(1)
    x = jax.pure_callback(wait_for_the_other, jax.ShapeDtypeStruct(x.shape, x.dtype), x)
    return {"y": x * sw.gain + sw.eye + shared, "flag": sw.flag}


devices = jax.devices()
assert len(devices) == 2, devices
on = OnDevices(fn, devices, (0, Switch(gain=0, flag=0, eye=None), None))
x, gain, flag = np.arange(8.0), np.arange(8.0) + 10.0, 3.0 * np.arange(8.0)
placed = on.place(x, Switch(gain, flag, 0.5), 2.0)
for device, args in zip(devices, placed):  # each slice on its own device, shared values copied
    assert {leaf.devices().pop() for leaf in jax.tree_util.tree_leaves(args)} == {device}
    assert args[0].shape == (4,)
on.compile(placed)
n_traces = len(traces)
out = on.run(placed)
out = on.run(placed)  # the executables are reused
assert len(traces) == n_traces, "traced again"
np.testing.assert_array_equal(out["y"], x * gain + 0.5 + 2.0)
np.testing.assert_array_equal(out["flag"], flag)
print("OK")
"""


def test_two_devices_run_their_slices_at_the_same_time(tmp_path):
    """Two forced CPU devices: slices placed on their own devices, both executables running at
    once (each waits at a barrier for the other: one thread calling them in turn never returns),
    the outputs in order, no second trace."""
    script = tmp_path / "two_devices.py"
    script.write_text(TWO_DEVICES)
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "")
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count=2".strip()
    proc = subprocess.run(
        [sys.executable, str(script), str(ROOT)],
        env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stderr[-3000:]


def test_outputs_without_the_run_axis_are_refused():
    device = jax.devices()[0]
    on = OnDevices(lambda x: {"mean": x.mean(0)}, [device, device], in_axes=(0,))
    with pytest.raises(ValueError, match="no run axis"):
        on(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="tuple"):
        OnDevices(lambda x: x, [device], in_axes=0)
