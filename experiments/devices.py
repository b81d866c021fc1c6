"""Independent runs over the devices of one host: one executable per device, one thread each.

The runs of a sweep never talk to each other, so n devices can each run their own slice of the
run axis with the program one device runs. ``OnDevices`` does that: it compiles ``jax.jit(fn)``
once per device (in parallel threads), places each device's slice there, and calls every device's
executable from its own host thread, so that no device waits for another.

Why not one SPMD program (``jax.shard_map``, or ``NamedSharding`` under ``jit``), measured on two
H100s (JAX 0.10.2, MJX 3.17, 2026-11-25): XLA's GPU compiler crashed (segmentation fault) on the
catching loop under ``shard_map``, with either network step (a network step alone compiled and
ran); the learner's Pallas Triton kernel has no partitioning rule for GSPMD; and with one host thread
calling the two devices' executables in turn, 65536 runs split over two devices ran at 0.89x of one
device running them all. With a thread per device, two devices ran 2.00x the steps/s of one (65536
runs per device). Our reading: a call returns only when its executable has finished (XLA's GPU
runtime reads the solver ``while_loop``'s condition back on the host), so a single thread runs the
devices one after the other. See docs/benchmarks_gpu.md.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np


def _is_none(x) -> bool:
    return x is None


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
    all runs in order, as on one device; calling the object does all three.
    """

    def __init__(self, fn, devices, in_axes: tuple):
        leaves = jax.tree_util.tree_leaves(in_axes, is_leaf=_is_none)
        if any(a not in (0, None) for a in leaves):
            raise ValueError(f"in_axes entries must be 0 or None, got {in_axes}")
        self.devices = list(devices)
        if not self.devices:
            raise ValueError("no devices given")
        self.in_axes = tuple(in_axes)
        self._jitted = jax.jit(fn)
        self._compiled = None
        self._pool = ThreadPoolExecutor(max_workers=len(self.devices))

    def place(self, *args) -> list[tuple]:
        """Each device's slice of ``args`` (a tuple of arguments per device), on that device."""
        if len(args) != len(self.in_axes):
            raise ValueError(f"{len(args)} arguments for {len(self.in_axes)} in_axes")
        n = len(self.devices)
        batched = []  # the leaves with the run axis

        def collect(ax, sub):
            if ax is not None:
                batched.extend(jax.tree_util.tree_leaves(sub))

        jax.tree_util.tree_map(collect, self.in_axes, args, is_leaf=_is_none)
        sizes = {np.shape(x)[0] if np.ndim(x) else None for x in batched}
        if len(sizes) != 1:
            raise ValueError(f"the batched arguments' run axes differ or are missing: {sizes}")
        (size,) = sizes
        if size % n:
            raise ValueError(f"{size} runs do not divide over {n} devices")
        per = size // n

        def part(i):
            def cut(ax, arg):
                if ax is None:
                    return arg
                return jax.tree_util.tree_map(lambda x: x[i * per : (i + 1) * per], arg)

            sliced = tuple(jax.tree_util.tree_map(cut, self.in_axes, args, is_leaf=_is_none))
            return jax.device_put(sliced, self.devices[i])

        return [part(i) for i in range(n)]

    def compile(self, placed: list[tuple]) -> OnDevices:
        """Compiles every device's executable, in parallel threads."""
        lowered = list(self._pool.map(lambda a: self._jitted.lower(*a).compile(), placed))
        self._compiled = lowered
        return self

    def run(self, placed: list[tuple]):
        """All runs' outputs (NumPy, run axis first, in order); each device called from its own
        thread."""
        if self._compiled is None:
            self.compile(placed)

        def one(i):
            out = self._compiled[i](*placed[i])
            return jax.tree_util.tree_map(np.asarray, out)  # waits for this device only

        outs = list(self._pool.map(one, range(len(placed))))
        return jax.tree_util.tree_map(lambda *x: np.concatenate(x), *outs)

    def __call__(self, *args):
        return self.run(self.place(*args))
