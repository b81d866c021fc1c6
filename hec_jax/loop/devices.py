"""Independent runs over the devices of one host: one executable per device, one thread each.

The runs of a sweep never talk to each other, so n devices can each run their own slice of the
run axis with the program one device runs. ``OnDevices`` does that: it compiles ``jax.jit(fn)``
once per device (in parallel threads), places each device's slice there, and calls every device's
executable from its own host thread, so that no device waits for another.

Measured on two H100s (JAX 0.10.2, MJX 3.17, 2026-11-25; docs/benchmarks_gpu.md):

- a thread per device: two devices ran 2.00x the steps/s of one (65536 runs per device);
- one host thread calling the two executables in turn: 65536 runs split over two devices ran at
  0.89x of one device running them all. Our reading: a call returns only when its executable has
  finished (XLA's GPU runtime reads the solver ``while_loop``'s condition back on the host), so a
  single thread runs the devices one after the other;
- one SPMD program instead: ``jax.shard_map`` of the catching loop crashed XLA's GPU compiler
  (segmentation fault; a network step alone compiled and ran); GSPMD (``NamedSharding`` under
  ``jit``, ``Sharded`` below) ran 1.88x with the XLA network step, and cannot split the learner's
  Pallas Triton kernel (a custom call without a partitioning rule).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np


def _is_none(x) -> bool:
    return x is None


def _checked(devices, in_axes) -> tuple[list, tuple]:
    """The devices as a list and ``in_axes`` as a tuple, refused where unusable."""
    if not isinstance(in_axes, tuple | list):
        raise ValueError(f"in_axes must be a tuple with an entry per argument, got {in_axes!r}")
    leaves = jax.tree_util.tree_leaves(in_axes, is_leaf=_is_none)
    if any(not (a is None or (type(a) is int and a == 0)) for a in leaves):
        raise ValueError(f"in_axes entries must be 0 or None, got {in_axes}")
    devices = list(devices)
    if not devices:
        raise ValueError("no devices given")
    return devices, tuple(in_axes)


def _run_axis_length(in_axes: tuple, args: tuple, n: int) -> int:
    """The run-axis length of ``args``, checked to be one length that divides over ``n``."""
    if len(args) != len(in_axes):
        raise ValueError(f"{len(args)} arguments for {len(in_axes)} in_axes")
    batched = []  # the leaves with the run axis

    def collect(ax, sub):
        if ax is not None:
            batched.extend(jax.tree_util.tree_leaves(sub))

    jax.tree_util.tree_map(collect, in_axes, args, is_leaf=_is_none)
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in batched}
    if len(sizes) != 1:
        raise ValueError(f"the batched arguments' run axes differ or are missing: {sizes}")
    (size,) = sizes
    if size % n:
        raise ValueError(f"{size} runs do not divide over {n} devices")
    return size


class OnDevices:
    """``fn(*args)`` with its runs split over ``devices``; outputs gathered as NumPy arrays.

    Args:
        fn: a function of arrays whose outputs all have the run axis first (per-run results).
        devices: the devices to use, e.g. ``jax.devices()``.
        in_axes: as ``jax.vmap``'s, a pytree prefix per argument of ``fn``: 0 where the leaves
            have the run axis (split across devices), None where they have not (copied to every
            device). The run axis must divide by ``len(devices)``.

    ``place(*args)`` puts each device's slice on it (do it once, outside a timed region);
    ``compile(placed)`` compiles ahead of time (optional); ``run(placed)`` returns the outputs of
    all runs in order, as on one device; calling the object does all three. The executables are
    compiled once, for the shapes and dtypes of the first placed arguments (a sweep's chunks all
    have the same); other shapes later raise a TypeError.
    """

    def __init__(self, fn, devices, in_axes: tuple):
        self.devices, self.in_axes = _checked(devices, in_axes)
        self._jitted = jax.jit(fn)
        self._compiled = None
        self._pool = ThreadPoolExecutor(max_workers=len(self.devices))

    def place(self, *args) -> list[tuple]:
        """Each device's slice of ``args`` (a tuple of arguments per device), on that device."""
        n = len(self.devices)
        per = _run_axis_length(self.in_axes, args, n) // n

        def part(i):
            def cut(ax, arg):
                if ax is None:
                    return arg
                return jax.tree_util.tree_map(lambda x: x[i * per : (i + 1) * per], arg)

            sliced = tuple(jax.tree_util.tree_map(cut, self.in_axes, args, is_leaf=_is_none))
            return jax.device_put(sliced, self.devices[i])

        return [part(i) for i in range(n)]

    def compile(self, placed: list[tuple]) -> OnDevices:
        """Compiles every device's executable, in parallel threads (traced and lowered in the
        calling thread, under its JAX settings).
        """
        lowered = [self._jitted.lower(*a) for a in placed]
        self._compiled = list(self._pool.map(lambda low: low.compile(), lowered))
        return self

    def run(self, placed: list[tuple]):
        """All runs' outputs (NumPy, run axis first, in order); each device called from its own
        thread.
        """
        if self._compiled is None:
            self.compile(placed)

        def one(i):
            out = self._compiled[i](*placed[i])
            return jax.tree_util.tree_map(np.asarray, out)  # waits for this device only

        outs = list(self._pool.map(one, range(len(placed))))
        sizes = [_run_axis_length(self.in_axes, p, 1) for p in placed]
        for size, out in zip(sizes, outs, strict=True):  # every output must be per run
            for path, leaf in jax.tree_util.tree_leaves_with_path(out):
                if leaf.ndim == 0 or leaf.shape[0] != size:
                    raise ValueError(
                        f"output {jax.tree_util.keystr(path)} of shape {leaf.shape} has no run "
                        f"axis of {size} first: OnDevices gathers per-run outputs only"
                    )
        return jax.tree_util.tree_map(lambda *x: np.concatenate(x), *outs)

    def __call__(self, *args):
        """``run(place(*args))``."""
        return self.run(self.place(*args))


class Sharded:
    """The same interface as ``OnDevices``, as one SPMD program: ``jax.jit(fn)`` with the run
    axis laid over ``devices`` by ``NamedSharding`` (GSPMD), the unbatched arguments replicated.

    The standard JAX way: one program, placed by XLA. On two H100s it ran 1.88x one device
    against ``OnDevices``' 2.00x (XLA network step, 65536 runs per device; docs/benchmarks_gpu.md,
    ``benchmarks/sweep.py --spmd``). A custom call without a partitioning rule, such as the
    learner's Pallas Triton kernel, cannot be split by GSPMD (``experiments/sweep.py --spmd``
    refuses ``--kernel triton`` on GPUs). Outputs come back as NumPy arrays, as from ``OnDevices``.
    """

    def __init__(self, fn, devices, in_axes: tuple):
        from jax.sharding import Mesh, NamedSharding
        from jax.sharding import PartitionSpec as P

        self.devices, self.in_axes = _checked(devices, in_axes)
        mesh = Mesh(np.asarray(self.devices), ("runs",))
        self._runs, self._copy = NamedSharding(mesh, P("runs")), NamedSharding(mesh, P())
        self._jitted = jax.jit(fn)
        self._compiled = None

    def place(self, *args) -> tuple:
        """``args`` on the devices: the run axis split, the rest on every device."""
        _run_axis_length(self.in_axes, args, len(self.devices))

        def put(ax, sub):
            return jax.device_put(sub, self._copy if ax is None else self._runs)

        return tuple(jax.tree_util.tree_map(put, self.in_axes, args, is_leaf=_is_none))

    def compile(self, placed: tuple) -> Sharded:
        """Compiles the program for the placed arguments (ahead of the first run)."""
        self._compiled = self._jitted.lower(*placed).compile()
        return self

    def run(self, placed: tuple):
        """Runs on the placed arguments; returns the outputs as NumPy, runs in order."""
        if self._compiled is None:
            self.compile(placed)
        return jax.tree_util.tree_map(np.asarray, self._compiled(*placed))

    def __call__(self, *args):
        """``run(place(*args))``."""
        return self.run(self.place(*args))
