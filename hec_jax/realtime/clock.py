"""Clocks of the control loop: the wall clock at 1 kHz, or none (un-timed, as fast as possible).

Both give times [s] since the start of an episode. :class:`WallClock` waits for a tick with a
sleep/busy-wait hybrid: ``time.sleep`` until ``spin_s`` before the tick (the kernel's timer slack
and the scheduler's wake-up latency are tens of microseconds on Linux), then spins on the
monotonic clock, so the CPU is free for the camera and eye most of each period and the tick
still starts within a few microseconds. :class:`FreeClock` has no wall time at all: its time is
the tick last waited for, so nothing is ever late and a run is a deterministic function of its
inputs (the un-timed mode of :mod:`hec_jax.realtime.runner`).
"""

from __future__ import annotations

import contextlib
import math
import mmap
import os
import select
import struct
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from typing import Protocol

import numpy as np


def monotonic_s() -> float:
    """[s] the system-wide monotonic clock (CLOCK_MONOTONIC: the same in every process)."""
    return time.clock_gettime(time.CLOCK_MONOTONIC)


_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def host_steal_ms(path: str = "/proc/stat") -> list[float]:
    """[ms] per CPU (cpu0, cpu1, ...): the time the hypervisor ran something else while this
    virtual CPU wanted to run (``steal`` of ``/proc/stat``, in clock ticks of 1 / SC_CLK_TCK s,
    usually 10 ms), cumulative since boot. Empty where the file or the column is missing (not
    Linux, or no steal accounting). Differences over an interval say how much of it each CPU
    was taken away: a slow frame with steal is the host's, not the program's.
    """
    try:
        with open(path) as f:
            lines = f.read().splitlines()
    except OSError:
        return []
    out = []
    for line in lines:
        name, *fields = line.split()
        if name.startswith("cpu") and name != "cpu":
            if len(fields) < 8:
                return []
            out.append(1e3 * int(fields[7]) / _CLOCK_TICKS)
    return out


def cpu_work_ms(matmuls: int, a) -> float:
    """[ms] this thread's own CPU time for ``matmuls`` products ``a @ a`` (a fixed piece of
    work: its time moves only with the CPU's speed; steal and other threads' turns do not
    count). With a multi-threaded BLAS the time is the calling thread's share only: set
    ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` to 1 before NumPy loads.
    """
    t0 = time.thread_time()
    for _ in range(matmuls):
        a @ a
    return 1e3 * (time.thread_time() - t0)


def speed_summary(samples_ms) -> dict:
    """{"n", "min", "p50", "p90", "max", "max_over_min"} of samples [ms] of one piece of work.

    Raises:
        ValueError: no samples, or one not finite and > 0.
    """
    import numpy as np

    s = np.asarray(samples_ms, float)
    if s.size == 0 or not np.all(np.isfinite(s) & (s > 0)):
        raise ValueError(f"samples must be finite times > 0, got {samples_ms!r}")
    p = {k: float(np.percentile(s, q)) for k, q in (("p50", 50), ("p90", 90))}
    return {"n": int(s.size), "min": float(s.min()), **p, "max": float(s.max()),
            "max_over_min": float(s.max() / s.min())}  # fmt: skip


def probe_cpu_speed(seconds: float, gap_s: float = 0.5, matmuls: int = 200) -> dict:
    """{cpu: :func:`speed_summary`}: every ``gap_s`` [s] for ``seconds`` [s] the calling thread
    moves to the next CPU of its affinity (round robin) and times :func:`cpu_work_ms` of a fixed
    200 x 200 float64 matrix there; the affinity is restored after. A CPU that runs at one speed
    gives the same time every time; a virtual CPU sharing its physical core or clock with busy
    tenants gives a spread (which the host does not count as steal). Keys: CPU numbers as
    strings ("None" where the platform has no affinity).

    Raises:
        ValueError: ``seconds`` not > 0, ``gap_s`` < 0 or ``matmuls`` < 1.
    """
    import numpy as np

    if not seconds > 0 or not gap_s >= 0 or int(matmuls) != matmuls or matmuls < 1:
        raise ValueError(
            f"need seconds > 0, gap_s >= 0 and matmuls >= 1, got {seconds}, {gap_s}, {matmuls}"
        )
    a = np.random.default_rng(0).random((200, 200))
    movable = hasattr(os, "sched_setaffinity")
    old = os.sched_getaffinity(0) if movable else None
    cpus = sorted(old) if movable else [None]
    samples: dict = {c: [] for c in cpus}
    t_end, i = time.monotonic() + seconds, 0
    try:
        while time.monotonic() < t_end:
            cpu = cpus[i % len(cpus)]
            if cpu is not None:
                os.sched_setaffinity(0, {cpu})
                time.sleep(0.001)  # the move happens before the clock starts
            samples[cpu].append(cpu_work_ms(int(matmuls), a))
            i += 1
            time.sleep(gap_s)
    finally:
        if movable:
            os.sched_setaffinity(0, old)
    return {str(c): speed_summary(s) for c, s in samples.items() if s}


class Clock(Protocol):
    """A control loop's clock (times [s] since :meth:`start`)."""

    def start(self, lead_s: float = 0.0) -> float:
        """Starts the episode's time ``lead_s`` from now; returns its origin (monotonic [s])."""
        ...

    def now(self) -> float:
        """[s] time since the origin."""
        ...

    def wait_until(self, t: float) -> float:
        """Returns at time ``t`` [s] or at once if it has passed; returns :meth:`now`."""
        ...


class WallClock:
    """The monotonic wall clock; :meth:`wait_until` sleeps, then spins the last ``spin_s``.

    Args:
        spin_s: [s] busy-wait before each tick (longer: fewer late wake-ups, more CPU).
    """

    def __init__(self, spin_s: float = 2e-4):
        if not spin_s >= 0:
            raise ValueError(f"spin_s must be >= 0, got {spin_s}")
        self.spin_s = float(spin_s)
        self.origin = monotonic_s()

    def start(self, lead_s: float = 0.0) -> float:
        """Starts the time ``lead_s`` [s] from now; returns the origin (monotonic [s])."""
        self.origin = monotonic_s() + lead_s
        return self.origin

    def now(self) -> float:
        """[s] since the origin."""
        return monotonic_s() - self.origin

    def wait_until(self, t: float) -> float:
        """Sleeps until ``spin_s`` before ``t`` [s], spins to ``t``; returns :meth:`now`."""
        target = self.origin + t
        rest = target - monotonic_s() - self.spin_s
        if rest > 0:
            time.sleep(rest)
        now = monotonic_s()
        while now < target:
            now = monotonic_s()
        return now - self.origin


class FreeClock:
    """No wall time: the time is the last tick waited for (un-timed runs)."""

    def __init__(self):
        self.origin = 0.0
        self._t = 0.0

    def start(self, lead_s: float = 0.0) -> float:
        """Resets the time to 0; returns the origin (0)."""
        self._t = 0.0
        return self.origin

    def now(self) -> float:
        """[s] the tick last waited for."""
        return self._t

    def wait_until(self, t: float) -> float:
        """Sets the time to ``t`` [s] (never goes back) and returns it."""
        self._t = max(self._t, t)
        return self._t


class realtime_priority:
    """Context manager: the calling thread (the control loop) under ``SCHED_FIFO`` at
    ``priority`` (1-99; 0: leave the scheduling alone) and every other thread of this process at
    ``priority - 1``; normal scheduling again on exit.

    A real-time control loop runs so (a robot's controller on a PREEMPT_RT kernel): ordinary
    processes on the same cores no longer preempt it. The other threads are XLA's: its CPU runtime
    hands independent parts of the jitted step to its thread pool while the calling thread waits,
    so they must not wait behind ordinary processes either, and they must never preempt the loop
    (one below it). Needs CAP_SYS_NICE (root); the kernel's real-time throttling
    (``sched_rt_runtime_us``, 95% by default) still leaves the other processes some time if the
    loop spins. Threads started inside the block inherit the calling thread's.

    ``pool_idle`` (with ``priority`` 0, where ``SCHED_FIFO`` is refused): every thread but the
    calling one under ``SCHED_IDLE`` instead. The same order as above among the process's
    threads: XLA's threads run while the loop waits for them and give way the moment it is
    runnable (without it they share its CPU as equals and preempt it while it spins for its next
    tick: docs/realtime.md, "XLA's pool under SCHED_IDLE"). But they then wait behind every
    ordinary process on their CPU, and the loop waits for them: a loop whose CPU is not its own
    alone (``pinned`` to an isolated CPU) stalls for another process's whole burst there. On
    exit each thread gets its own scheduling back, which Linux allows only with CAP_SYS_NICE or
    a nice limit (RLIMIT_NICE) of 20: :func:`pool_idle_refused` says beforehand.

    Raises:
        PermissionError: not allowed to change the scheduling (on exit, with ``pool_idle``: not
            allowed to restore a thread's, unless an exception is already on its way).
    """

    def __init__(self, priority: int, pool_idle: bool = False):
        if not 0 <= priority <= 99:
            raise ValueError(f"priority must be in 0..99, got {priority}")
        self.priority = int(priority)
        self.pool_idle = bool(pool_idle) and not self.priority
        self._saved: dict[int, tuple[int, int]] = {}

    @property
    def idle_threads(self) -> dict[int, tuple[int, int]]:
        """Inside the block with ``pool_idle``: the threads put under ``SCHED_IDLE``, each with
        its own (policy, priority) from before (empty otherwise).
        """
        return dict(self._saved)

    def __enter__(self):
        if self.priority:
            set_scheduling(os.SCHED_FIFO, max(self.priority - 1, 1))
            set_thread_scheduling(threading.get_native_id(), os.SCHED_FIFO, self.priority)
        elif self.pool_idle:
            me = threading.get_native_id()
            for tid in _threads():
                if tid == me:
                    continue
                with contextlib.suppress(ProcessLookupError):
                    saved = os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority
                    os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
                    self._saved[tid] = saved
        return self

    def __exit__(self, exc_type, *exc):
        if self.priority:
            set_scheduling(os.SCHED_OTHER, 0)
        failed = []
        for tid, (policy, prio) in self._saved.items():
            try:
                os.sched_setscheduler(tid, policy, os.sched_param(prio))
            except ProcessLookupError:
                pass
            except PermissionError:
                failed.append(tid)
        self._saved = {}
        if failed and exc_type is None:
            raise PermissionError(
                f"{len(failed)} threads stay under SCHED_IDLE: leaving it needs CAP_SYS_NICE or a "
                "nice limit of 20 (pool_idle_refused says so before a run)"
            )


# the pool's watchdog (:class:`pool_rescue`), run by this Python with ``-c`` after
# _DIE_WITH_PARENT; argv: the shared file, after_ns, poll_s, then "tid:policy:priority" for each
# thread. Its file holds RESCUE_WORDS int64: [0] when the loop's current jitted step began
# (CLOCK_MONOTONIC ns; 0: none), [1] rescues, [2] ns spent rescued (closed rescues), [3] 1 once
# it runs, [4] scheduling changes refused (other than for a thread that has ended), [5] when the
# rescue in progress began (0: none)
RESCUE_WORDS = 6
_RESCUE_PROGRAM = """
import mmap, struct, sys, time
path, after_ns, poll_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
threads = [tuple(int(x) for x in a.split(":")) for a in sys.argv[4:]]
Q = struct.Struct("<q")
with open(path, "r+b") as f:
    m = mmap.mmap(f.fileno(), 0)  # the whole file: RESCUE_WORDS int64
errors = 0


def put(idle):
    global errors
    for tid, policy, prio in threads:
        try:
            if idle:
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            else:
                os.sched_setscheduler(tid, policy, os.sched_param(prio))
        except ProcessLookupError:
            pass
        except OSError:
            errors += 1
            Q.pack_into(m, 32, errors)


held = since = n = total = 0
Q.pack_into(m, 24, 1)
while True:
    time.sleep(poll_s)
    began = Q.unpack_from(m, 0)[0]
    now = time.monotonic_ns()
    if began and now - began > after_ns:  # a step has waited too long: the pool its own again
        if not held:
            held, since, n = 1, now, n + 1
            Q.pack_into(m, 40, since)
            put(False)
            Q.pack_into(m, 8, n)
    elif held:  # no step waiting too long: the pool idle again
        put(True)
        held, total = 0, total + now - since
        Q.pack_into(m, 16, total)
        Q.pack_into(m, 40, 0)
"""


class pool_rescue:
    """Context manager: bounds :class:`realtime_priority`'s ``pool_idle`` hazard. A watchdog
    process on ``cpus`` (not the loop's) watches the loop's jitted step; once one step has
    waited longer than ``after_us``, it gives the threads under ``SCHED_IDLE`` their own
    scheduling back until that step is done, then puts them under ``SCHED_IDLE`` again.

    Why: under ``SCHED_IDLE`` XLA's pool runs only while nothing else wants the loop's CPU; a
    step that waits for the pool while another process bursts there waits for the whole burst
    (60 ms for a 60 ms burst; docs/realtime.md, "XLA's pool under SCHED_IDLE"). Rescued, the
    pool is the burst's equal again, as it is without ``pool_idle``, so a stall lasts about
    ``after_us`` + ``poll_us`` + the kernel's time to run it. Leaving ``SCHED_IDLE`` needs
    what :func:`pool_idle_refused` checks.

    The loop marks each step: ``marker[0] = time.monotonic_ns()`` before it, ``0`` after.

    Args:
        threads: the threads under ``SCHED_IDLE`` and their own (policy, priority)
            (:attr:`realtime_priority.idle_threads`); empty, or ``after_us`` None: nothing runs
            and ``marker`` is None.
        after_us: [us] how long a step may wait before its pool is rescued.
        poll_us: [us] the watchdog's sleep between looks.
        cpus: the watchdog's CPUs (None: wherever the kernel puts it).
        nice: the watchdog's nice value (-20..19).
        ready_timeout_s: [s] to wait for the watchdog to start.

    Raises:
        ValueError: ``after_us`` or ``poll_us`` not a positive number.
        RuntimeError: on entry, the watchdog did not start in time.
    """

    def __init__(
        self,
        threads: dict[int, tuple[int, int]],
        after_us: float | None,
        poll_us: float = 250.0,
        cpus=None,
        nice: int = 0,
        ready_timeout_s: float = 10.0,
    ):
        if after_us is not None and not (math.isfinite(after_us) and after_us > 0):
            raise ValueError(f"after_us must be None or > 0, got {after_us!r}")
        if not (math.isfinite(poll_us) and poll_us > 0):
            raise ValueError(f"poll_us must be > 0, got {poll_us!r}")
        self.threads = dict(threads) if after_us is not None else {}
        self.after_us, self.poll_us = after_us, float(poll_us)
        self.cpus = set(cpus) if cpus else None
        self.nice, self.ready_timeout_s = int(nice), float(ready_timeout_s)
        self.marker: np.ndarray | None = None
        self.summary: dict | None = None
        self._proc = self._map = self._path = None

    def __enter__(self):
        if not self.threads:
            return self
        fd, self._path = tempfile.mkstemp(
            prefix="hec_pool_rescue_", dir="/dev/shm" if os.path.isdir("/dev/shm") else None
        )
        try:
            os.write(fd, bytes(8 * RESCUE_WORDS))
            self._map = mmap.mmap(fd, 8 * RESCUE_WORDS)
        except BaseException:
            os.unlink(self._path)
            raise
        finally:
            os.close(fd)
        self.marker = np.ndarray((RESCUE_WORDS,), np.int64, buffer=self._map)
        args = [self._path, str(int(self.after_us * 1e3)), repr(self.poll_us * 1e-6)]
        args += [f"{tid}:{policy}:{prio}" for tid, (policy, prio) in self.threads.items()]
        code = _DIE_WITH_PARENT.format(parent=os.getpid()) + _RESCUE_PROGRAM
        try:
            self._proc = subprocess.Popen([sys.executable, "-c", code, *args])
            if self.cpus:
                pin_process(self._proc.pid, self.cpus)
            if self.nice:
                os.setpriority(os.PRIO_PROCESS, self._proc.pid, self.nice)
            end = time.monotonic() + self.ready_timeout_s
            while self.marker[3] != 1:
                if self._proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError(
                        "the pool's watchdog did not start"
                        f" (exit status {self._proc.poll()}; see its stderr)"
                    )
                time.sleep(1e-3)
            # both sides have it mapped: nothing is left behind if this process is killed
            os.unlink(self._path)
            self._path = None
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc):
        if self._proc is None and self._map is None:
            return
        alive = self._proc is not None and self._proc.poll() is None
        status = None if self._proc is None else self._proc.poll()
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait()
        if self.marker is not None:
            open_ns = time.monotonic_ns() - self.marker[5] if self.marker[5] else 0
            self.summary = {
                "after_us": self.after_us,
                "poll_us": self.poll_us,
                "rescues": int(self.marker[1]),
                # a rescue still in progress at the end included
                "rescued_ms": float(self.marker[2] + open_ns) * 1e-6,
                # scheduling changes the watchdog was refused (the pool then not rescued)
                "refused_changes": int(self.marker[4]),
                # the watchdog ran to the end (False: it died; its exit status)
                "alive_to_the_end": alive,
                "exit_status": status,
            }
            if not alive or self.marker[4]:
                warnings.warn(
                    f"the pool's watchdog {'died' if not alive else 'ran'} (exit status "
                    f"{status}; {int(self.marker[4])} scheduling changes refused): the idle "
                    "pool was not always rescued",
                    RuntimeWarning,
                    stacklevel=2,
                )
        self.marker = None
        if self._map is not None:
            self._map.close()
        if self._path is not None:
            with contextlib.suppress(OSError):
                os.unlink(self._path)
        self._proc = self._map = self._path = None


# the kernel's real-time bandwidth (Linux): real-time threads of a CPU run at most
# ``sched_rt_runtime_us`` of every ``sched_rt_period_us`` (-1: no limit)
RT_RUNTIME_FILE = "/proc/sys/kernel/sched_rt_runtime_us"
RT_PERIOD_FILE = "/proc/sys/kernel/sched_rt_period_us"


def _read_int(path: str) -> int | None:
    try:
        with open(path) as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def rt_budget_rest_s(
    policy: int | None = None,
    period_us: int | None = None,
    runtime_us: int | None = None,
    margin_s: float = 0.01,
) -> float:
    """[s] to sleep before real-time work so that the kernel's real-time throttling cannot
    stop it: the part of each period real-time threads may not use, plus ``margin_s``; 0 under
    normal scheduling or without a limit.

    Past ``runtime_us`` of real-time work on a CPU within one ``period_us`` (95% of each
    second by default), the kernel stops that CPU's real-time threads until the period ends:
    a stall of up to ``period_us - runtime_us`` (50 ms). Work that keeps a CPU busy for over a
    second at real-time priority (compiling the step before the first episode) hits it every
    second, and when the last hit falls on the first ticks, the loop skips them
    (docs/realtime.md, "The start-up stall"). A sleep of at least the unusable part, ending
    where the real-time work begins, leaves every period that overlaps that work under the
    limit as long as the work itself stays under it (a tick's duty is well under 95%).

    Args:
        policy: the calling thread's scheduling policy (None: read it).
        period_us: [us] the kernel's real-time period (None: read it; unreadable: no rest).
        runtime_us: [us] the real-time threads' share of it (None: read it; unreadable or -1:
            no rest).
        margin_s: [s] added to the rest.
    """
    policy = os.sched_getscheduler(0) if policy is None else policy
    if policy not in (os.SCHED_FIFO, os.SCHED_RR):
        return 0.0
    period_us = _read_int(RT_PERIOD_FILE) if period_us is None else period_us
    runtime_us = _read_int(RT_RUNTIME_FILE) if runtime_us is None else runtime_us
    if period_us is None or runtime_us is None or runtime_us < 0 or runtime_us >= period_us:
        return 0.0
    return (period_us - runtime_us) * 1e-6 + margin_s


def realtime_refused(priority: int) -> str | None:
    """Why ``SCHED_FIFO`` at ``priority`` is refused to this process, as one line (None: it is
    allowed, or ``priority`` is 0). Tried on the calling thread and undone at once, so a run
    can say so before it compiles anything.
    """
    if not priority:
        return None
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except PermissionError as err:
        return (
            f"real-time scheduling (SCHED_FIFO {priority}) is not permitted here ({err.strerror}):"
            " it needs root or CAP_SYS_NICE and a real-time budget for this process's cgroup;"
            " run without --rt-priority, --camera-priority and --eye-priority"
        )
    os.sched_setscheduler(0, policy, param)
    return None


def pool_idle_refused(pool_idle: bool) -> str | None:
    """Why :class:`realtime_priority`'s ``pool_idle`` cannot be undone here, as one line (None:
    it can, or ``pool_idle`` is False). A thread is put under ``SCHED_IDLE`` and back at once:
    leaving it needs CAP_SYS_NICE or a nice limit (RLIMIT_NICE) of 20.
    """
    if not pool_idle:
        return None
    if not hasattr(os, "SCHED_IDLE"):
        return "SCHED_IDLE needs Linux: run without --pool-idle"
    why: list[str] = []

    def probe():
        tid = threading.get_native_id()
        policy, param = os.sched_getscheduler(tid), os.sched_getparam(tid)
        os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        try:
            os.sched_setscheduler(tid, policy, param)
        except PermissionError as err:
            why.append(err.strerror)

    t = threading.Thread(target=probe)  # a thread of its own: one left idle harms nothing
    t.start()
    t.join()
    if why:
        return (
            f"--pool-idle could not be undone here ({why[0]}): leaving SCHED_IDLE needs "
            "CAP_SYS_NICE or a nice limit (ulimit -e) of 20; run without --pool-idle"
        )
    return None


def _threads() -> list[int]:
    """The thread ids of this process (Linux)."""
    return [int(tid) for tid in os.listdir("/proc/self/task")]


def set_thread_scheduling(tid: int, policy: int, priority: int) -> None:
    """``sched_setscheduler`` for thread ``tid`` (Linux; a thread that has ended is skipped)."""
    with contextlib.suppress(ProcessLookupError):
        os.sched_setscheduler(tid, policy, os.sched_param(priority))


def set_scheduling(policy: int, priority: int) -> None:
    """``sched_setscheduler`` for every thread of this process (Linux)."""
    for tid in _threads():
        set_thread_scheduling(tid, policy, priority)


class pinned:
    """Context manager: every thread of this process (the control loop and XLA's pool threads,
    which run parts of each jitted step) on the CPUs ``cpus``; their previous CPU sets on exit.

    The step's hand-offs to XLA's threads then stay on the loop's CPU (no wake-up of another
    virtual CPU; per tick, the process's CPU time halves: docs/realtime.md), and the other CPUs
    are left to the camera and the eye. Threads started inside the block inherit the
    calling thread's CPUs. ``cpus`` None or empty: nothing changes.
    """

    def __init__(self, cpus):
        self.cpus = set(cpus) if cpus else set()
        self._old: dict[int, set[int]] = {}

    def __enter__(self):
        if self.cpus and hasattr(os, "sched_setaffinity"):
            for tid in _threads():
                with contextlib.suppress(ProcessLookupError):
                    self._old[tid] = os.sched_getaffinity(tid)
                    os.sched_setaffinity(tid, self.cpus)
        return self

    def __exit__(self, *exc):
        for tid, cpus in self._old.items():
            with contextlib.suppress(ProcessLookupError):
                os.sched_setaffinity(tid, cpus)
        self._old = {}


def pin_process(pid: int, cpus) -> None:
    """Every thread of process ``pid`` on the CPUs ``cpus`` (Linux; threads that end meanwhile
    are skipped).
    """
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(int(tid), set(cpus))


# Linux's PM QoS interface for the CPUs' wake-up latency: a request holds while the file is open
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"


class cpu_latency_request:
    """Context manager: asks the kernel for a CPU wake-up latency of at most ``latency_us``
    [us] while the loop runs (Linux PM QoS: an ``int32`` written to :data:`CPU_LATENCY_DEVICE`,
    held while the file stays open, withdrawn on exit); None: nothing is asked.

    With 0 (what ``cyclictest`` asks by default, and a real-time Linux controller's usual
    setting) an idle CPU polls instead of halting. On the 2-core KVM guest the loop sleeps
    most of each 1 ms period: every halt left the virtual CPU to the host, and the next tick
    found its caches cold (a tick's CPU time 2x its hot cost, a tail of 3-5x; measured in
    docs/realtime.md, "Idle CPUs that poll"). Polling costs the CPUs' idle time (power on a
    real machine, host CPU time on a virtual one). Needs root.

    Args:
        latency_us: [us] the largest wake-up latency allowed (0 .. 2**31 - 1); None: no request.
        device: the PM QoS file (tests pass a temporary file).

    Raises:
        ValueError: ``latency_us`` out of range.
        PermissionError, FileNotFoundError: on entry, the request cannot be made here.
    """

    def __init__(self, latency_us: int | None, device: str = CPU_LATENCY_DEVICE):
        if latency_us is not None and not (isinstance(latency_us, int) and 0 <= latency_us < 2**31):
            raise ValueError(f"latency_us must be None or an integer >= 0, got {latency_us!r}")
        self.latency_us, self.device = latency_us, device
        self._fd: int | None = None

    def __enter__(self):
        if self.latency_us is not None:
            fd = os.open(self.device, os.O_WRONLY)
            try:
                os.write(fd, struct.pack("i", self.latency_us))
            except BaseException:
                os.close(fd)
                raise
            self._fd = fd
        return self

    def __exit__(self, *exc):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def cpu_latency_refused(latency_us: int | None, device: str = CPU_LATENCY_DEVICE) -> str | None:
    """Why :class:`cpu_latency_request` of ``latency_us`` cannot be made here, as one line
    (None: it can, or ``latency_us`` is None). Opens the file for writing and closes it at once
    (no request is made), so a run can say so before it compiles anything.
    """
    if latency_us is None:
        return None
    try:
        os.close(os.open(device, os.O_WRONLY))
    except OSError as err:
        return (
            f"the CPU wake-up latency request ({device}) cannot be made here ({err.strerror}):"
            " it needs Linux's PM QoS interface and root; run without --cpu-latency-us"
        )
    return None


# what an idle filler runs (one process per CPU): a busy loop, or a stream through 2 x 128 MiB
IDLE_FILLERS = {
    "spin": "while True: pass",
    "memory": "import numpy as np\na = np.ones(1 << 24)\nb = np.empty_like(a)\n"
    "while True: np.copyto(b, a)",
}


# the first lines of every filler: it dies with the thread that started it (Linux's
# PR_SET_PDEATHSIG, SIGKILL), and exits at once if its parent is already gone, so a run that is
# killed leaves no filler behind
_DIE_WITH_PARENT = (
    "import ctypes, os, signal\n"
    "ctypes.CDLL(None).prctl(1, signal.SIGKILL)\n"
    "if os.getppid() != {parent}:\n"
    "    os._exit(0)\n"
)
# then, for :class:`idle_filler`, one byte on its stdout, which it waits for before it lowers
# the filler's priority (a filler starting up at SCHED_IDLE on a busy CPU got no time for
# seconds, and was not yet bound to its parent)
_SAY_READY = "os.write(1, b'.')\n"


def filler_command(kind: str, say_ready: bool = False) -> list[str]:
    """The command of one ``IDLE_FILLERS[kind]`` process (this Python), which dies with the
    calling thread (start it from a thread that lives as long as it should); with ``say_ready``
    it writes one byte (``.``) to its stdout once it is bound to that thread, before its work.
    """
    head = _DIE_WITH_PARENT.format(parent=os.getpid()) + (_SAY_READY if say_ready else "")
    return [sys.executable, "-c", head + IDLE_FILLERS[kind]]


FILLER_START_TIMEOUT_S = 60.0  # for a filler's interpreter to start (a busy CPU: seconds)


class idle_filler:
    """Context manager: one process per CPU of ``cpus`` running ``IDLE_FILLERS[kind]`` at
    ``SCHED_IDLE`` (Linux), so those CPUs never go idle; any other task on them preempts it at
    once. Stopped and reaped on exit; killed with the calling thread if that dies first
    (:func:`filler_command`). ``kind`` None: nothing.

    Why: on the 2-core KVM guest the jitter probe's ticks on one CPU end past 1 ms more often
    with the other CPU idle than with it loaded, while the real-time run leaves the second CPU
    idle most of each frame period; in the real-time runs it was not shown to help
    (docs/realtime.md, "The other CPU kept busy"). Start it before taking real-time priority (a
    child inherits the parent's scheduling).

    Raises:
        ValueError: an unknown ``kind``.
        RuntimeError: a filler did not start (say it was bound to this thread) within
            ``FILLER_START_TIMEOUT_S``.
    """

    def __init__(self, kind: str | None, cpus):
        if kind is not None and kind not in IDLE_FILLERS:
            raise ValueError(f"idle filler must be None or one of {sorted(IDLE_FILLERS)}: {kind!r}")
        self.kind, self.cpus = kind, sorted(cpus)
        self.procs: list = []

    def __enter__(self):
        if self.kind is None:
            return self
        try:
            for cpu in self.cpus:
                p = subprocess.Popen(filler_command(self.kind, True), stdout=subprocess.PIPE)
                self.procs.append(p)
                # bound to this thread (its first lines, run at this process's priority)
                try:
                    ready, _, _ = select.select([p.stdout], [], [], FILLER_START_TIMEOUT_S)
                    started = os.read(p.stdout.fileno(), 1) if ready else b""
                finally:
                    p.stdout.close()
                if started != b".":
                    why = "exited" if started == b"" and ready else "did not start"
                    raise RuntimeError(
                        f"the idle filler {why} before saying it was bound to this process"
                        f" (within {FILLER_START_TIMEOUT_S} s)"
                    )
                os.sched_setscheduler(p.pid, os.SCHED_IDLE, os.sched_param(0))
                pin_process(p.pid, {cpu})
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
            p.wait()
        self.procs = []
