"""Shared memory between the control process and its camera and eye processes (NumPy boundary).

Two containers, both lock-free for the writer (the 1 kHz control loop never waits on a reader):

* :class:`Board`: one record of named float64 fields under a sequence lock. The writer makes the
  sequence odd, writes the fields, makes it even again; a reader copies the record and retries
  if the sequence was odd or changed meanwhile. One writer per board.
* :class:`FrameRing`: the camera's frames, ``slots`` images with a :class:`Board` each and a
  ``latest`` board naming the newest complete frame. A reader takes the newest frame; if the
  camera overwrote its slot while it was being copied, the reader retries with the then newest.

Both live in ``multiprocessing`` ``RawArray`` buffers of the spawn context, so they are passed
to the child processes as ``Process`` arguments (inherited at start, never pickled later).
The sequence lock relies on stores becoming visible in program order (x86-64's memory model);
NumPy writes one field at a time.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Mapping

import numpy as np

_CTX = mp.get_context("spawn")


class Board:
    """A record of named float64 fields (each a fixed shape) under a sequence lock.

    Args:
        fields: {name: shape} of the record, e.g. ``{"t": (), "qpos": (5,)}``.
    """

    def __init__(self, fields: Mapping[str, tuple[int, ...]]):
        self.fields = {k: tuple(v) for k, v in fields.items()}
        sizes = [int(np.prod(s, dtype=int)) for s in self.fields.values()]
        self._slices = {}
        start = 1  # word 0: the sequence number
        for name, size in zip(self.fields, sizes, strict=True):
            self._slices[name] = slice(start, start + size)
            start += size
        self._raw = _CTX.RawArray("d", start)
        self._attach()

    def _attach(self) -> None:
        self._buf = np.frombuffer(self._raw, np.float64)

    def __getstate__(self):
        return {"fields": self.fields, "_slices": self._slices, "_raw": self._raw}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._attach()

    @property
    def seq(self) -> int:
        """The sequence number: even and increasing by 2 per completed write (0: never written)."""
        return int(self._buf[0])

    def write(self, **values) -> None:
        """Writes the given fields (the others keep their values); one writer only."""
        buf = self._buf
        buf[0] += 1.0  # odd: a write is in progress
        for name, v in values.items():
            buf[self._slices[name]] = np.ravel(v)
        buf[0] += 1.0

    def try_read(self) -> tuple[int, dict[str, np.ndarray]] | None:
        """(seq, {name: copy}) of a complete record, or None without waiting when a write is in
        progress or completed during the copy (for a reader on a deadline: it reads the record
        on its next try, and is never held up by a writer preempted mid-write).
        """
        buf = self._buf
        s0 = buf[0]
        if s0 % 2:
            return None
        copy = buf.copy()
        if buf[0] != s0:
            return None
        return int(s0), {
            name: copy[sl].reshape(self.fields[name]) for name, sl in self._slices.items()
        }

    def read(self, timeout_s: float = 1.0) -> tuple[int, dict[str, np.ndarray]]:
        """(seq, {name: copy}) of a complete record (retries while a write is in progress; a
        writer preempted mid-write is waited for, sleeping 20 us between tries after 50).

        Raises:
            TimeoutError: no consistent copy within ``timeout_s`` (a writer died mid-write).
        """
        tries, t_end = 0, None
        while True:
            record = self.try_read()
            if record is not None:
                return record
            tries += 1
            if tries > 50:
                t_end = time.monotonic() + timeout_s if t_end is None else t_end
                if time.monotonic() > t_end:
                    raise TimeoutError("no consistent read of the shared board")
                time.sleep(2e-5)


class FrameRing:
    """The camera's newest frames: ``slots`` images (H, W, 3) uint8 with their metadata.

    Args:
        height, width: [px].
        meta: {name: shape} of each frame's float64 metadata (``index`` is added).
        slots: ring length (>= 2: the writer fills one slot while readers copy another).
    """

    def __init__(self, height: int, width: int, meta: Mapping[str, tuple[int, ...]], slots=3):
        if slots < 2:
            raise ValueError(f"slots must be >= 2, got {slots}")
        self.shape = (int(height), int(width), 3)
        self.slots = int(slots)
        self._raw = _CTX.RawArray("B", self.slots * int(np.prod(self.shape)))
        fields = {"index": (), **meta}
        self.meta = [Board(fields) for _ in range(self.slots)]
        self.latest_board = Board({"index": ()})
        self._attach()

    def _attach(self) -> None:
        self._images = np.frombuffer(self._raw, np.uint8).reshape(self.slots, *self.shape)

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_images"}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._attach()

    def put(self, index: int, image: np.ndarray, **meta) -> None:
        """Publishes frame ``index`` (>= 0, increasing) with its metadata; one writer only."""
        slot = index % self.slots
        board = self.meta[slot]
        buf = board._buf
        buf[0] += 1.0
        self._images[slot] = image
        for name, v in dict(index=index, **meta).items():
            buf[board._slices[name]] = np.ravel(v)
        buf[0] += 1.0
        self.latest_board.write(index=index)

    def latest_index(self) -> int:
        """Index of the newest complete frame (-1: none yet)."""
        seq, rec = self.latest_board.read()
        return int(rec["index"]) if seq else -1

    def get(self, after: int = -1, max_tries: int = 100):
        """(image copy, metadata) of the newest frame if its index is > ``after``, else None
        (also if the camera kept overwriting the slot for ``max_tries`` tries).
        """
        for _ in range(max_tries):
            n = self.latest_index()
            if n <= after:
                return None
            slot = n % self.slots
            board = self.meta[slot]
            s0 = board._buf[0]
            if s0 % 2 == 1:
                continue
            image = self._images[slot].copy()
            meta = board._buf.copy()
            if board._buf[0] == s0 and int(meta[board._slices["index"]][0]) == n:
                return image, {
                    k: meta[sl].reshape(board.fields[k]) for k, sl in board._slices.items()
                }
        return None


def wait_for(predicate, timeout_s: float, poll_s: float = 1e-3, what: str = "condition") -> None:
    """Polls ``predicate()`` until true.

    Raises:
        TimeoutError: not true within ``timeout_s``.
    """
    t_end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > t_end:
            raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


class Images:
    """A fixed set of ``count`` images (H, W, 3) uint8 written once (calibration shots)."""

    def __init__(self, count: int, height: int, width: int):
        self.shape = (int(count), int(height), int(width), 3)
        self._raw = _CTX.RawArray("B", int(np.prod(self.shape)))
        self._ready = _CTX.RawArray("b", int(count))
        self._attach()

    def _attach(self) -> None:
        self._images = np.frombuffer(self._raw, np.uint8).reshape(self.shape)
        self._flags = np.frombuffer(self._ready, np.int8)

    def __getstate__(self):
        return {"shape": self.shape, "_raw": self._raw, "_ready": self._ready}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._attach()

    def put(self, i: int, image: np.ndarray) -> None:
        """Writes image ``i`` and marks it ready."""
        self._images[i] = image
        self._flags[i] = 1

    def ready(self, i: int) -> bool:
        """Whether image ``i`` has been written."""
        return bool(self._flags[i])

    def get(self, i: int) -> np.ndarray:
        """A copy of image ``i``."""
        return self._images[i].copy()
