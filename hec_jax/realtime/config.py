"""Settings of a real-time run (frozen; the CLI's flags come from here and the experiment's)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class RealtimeConfig:
    """How the loop runs on the clock; the task, eye and camera are the experiment's.

    The real-time loop runs one world (one network initialisation: seed 0 of a one-seed
    experiment with the experiment's ``seed``) under one condition.
    """

    condition: Literal["plain", "frozen", "learned"] = "learned"
    # [s] of real time: sets the number of swings to ceil(duration_s / swing_s) (training swings
    # of hitting; its continuous run comes on top); None: the preset's swings
    duration_s: float | None = None
    timed: bool = True  # False: no clock, as fast as possible (equivalence tests; eye truth only)
    # [us] busy-wait before each tick (sleep before that). Where SCHED_FIFO is refused and CPUs
    # are to spare, 1000 (spin through the whole period) met the tick's p99.9 in 6 of 7 runs on
    # two GPU machines' leases against 1 of 6 at 200 (docs/realtime.md, session 26); not at
    # SCHED_FIFO, which the kernel throttles past 95% of each second
    spin_us: float = 200.0
    lead_ms: float = 20.0  # [ms] from the start of an episode's clock to its first tick
    gc_off: bool = True  # no Python garbage collection during an episode (collected between)
    # before each episode's lead, the control thread (at real-time priority) sleeps the part of a
    # second the kernel keeps from real-time threads, plus 10 ms (``clock.rt_budget_rest_s``), so
    # its throttling cannot stop the first ticks after a busy set-up (the step's compilation
    # before episode 0 stalled them 34-45 ms: docs/realtime.md, "The start-up stall"). False:
    # no rest (the ablation); without real-time priority there is none either way
    rt_budget_rest: bool = True
    # the control process (its loop and XLA's pool threads) on the first CPU, the camera and eye
    # processes on the others (False: wherever the kernel puts them; docs/realtime.md)
    pin_cpus: bool = True
    # with pin_cpus, the eye's process also on the control loop's CPU, where it runs while the
    # loop waits for its next tick (the loop at real-time priority preempts it the moment it
    # wakes; so rt_priority > 0 is required). False: the eye on the other CPUs only (with two
    # CPUs it shares the second with the camera). On the 2-core VM it made the eye slower, not
    # faster (its wall time per frame p50 8 -> 12 ms, the state age worse): measured in
    # docs/realtime.md, "The eye on the control loop's CPU" (session 54); kept as the ablation
    eye_on_control_cpu: bool = False
    # SCHED_FIFO priority of the control loop while it runs (1-99); 0: normal scheduling (other
    # processes on the machine may preempt the loop)
    rt_priority: int = 0
    # with rt_priority 0 and pin_cpus: the control process's other threads (XLA's pool, which
    # runs parts of each jitted step while the loop waits) under SCHED_IDLE while the loop runs,
    # so they give way to the loop as they do one priority below it at SCHED_FIFO. Entering it
    # needs no privilege, undoing it CAP_SYS_NICE or a nice limit of 20 (a run checks first:
    # clock.pool_idle_refused). For a loop with a CPU of its own (isolated): without it, a loop
    # spinning through its period is preempted by the pool about 2.5 times a tick. The hazard:
    # while the loop waits for the pool, another process's burst on the loop's CPU stalls the
    # pool, and so the loop, for the whole burst instead of a share of it. Measured (both) in
    # docs/realtime.md, "XLA's pool under SCHED_IDLE". False: the pool at the loop's own
    # scheduling. Ignored with rt_priority > 0 (the pool then runs one priority below the loop)
    pool_idle: bool = False
    # with pool_idle: [us] how long one jitted step may wait for the pool before a watchdog
    # process (on the other CPUs) gives the pool its own scheduling back until that step is done
    # (``clock.pool_rescue``): the hazard above then stalls the loop for about this + the
    # watchdog's poll + the kernel's time to run the pool, not for the whole burst. 500: half the
    # period, 2.6-7x the step's median (70-190 us on the machines measured), chosen before any
    # run with it. None: no watchdog (pool_idle as in sessions 69-71). Measured in docs/realtime.md,
    # "A watchdog for the idle pool"
    pool_rescue_us: float | None = 500.0
    # [us] the watchdog's sleep between looks at the step (its cost: one wake-up each)
    pool_rescue_poll_us: float = 250.0
    # [us] the CPUs' wake-up latency asked of the kernel while the loop runs (Linux PM QoS,
    # /dev/cpu_dma_latency; root): 0 makes idle CPUs poll instead of halting, as cyclictest
    # does. On the 2-core KVM guest this took the missed deadlines from 0.35-1.0% to 0.01-0.05%
    # (docs/realtime.md, "Idle CPUs that poll"). None: nothing asked (the machine's setting)
    cpu_latency_us: int | None = None
    # SCHED_FIFO priority of the camera process once ready (below rt_priority); 0: normal
    # scheduling. Its load is bounded (one render per frame time).
    camera_priority: int = 0
    # the same for the eye. Its load is not bounded: a search from scratch after a lost track
    # takes 0.3-0.7 s of CPU; at real-time priority with the loop and the camera it can exhaust
    # the kernel's real-time budget (95% of each second), which then stalls all of them for the
    # rest of the second.
    eye_priority: int = 0
    # the eye tells its tracker the frame times it never saw (frames dropped while it was busy,
    # or not exposed) before the next frame (``BoxTracker.skip``), so that frame is predicted at
    # its own time; False: every frame processed is taken as 1 / fps after the last (as before
    # 2026-11-26, for the ablation). The simulated camera loop drops no frame: no difference there.
    eye_skips_unseen: bool = True
    # the eye's re-acquisition when a tracked fit fails: a search around the predicted pose with
    # this many start rotations before the search from scratch (``TrackConfig.local_starts``);
    # set in the camera's tracker for the real-time run and its simulated twin alike. On the
    # 2-core CPU it turned most of the eye's 0.3-0.8 s searches into 64-101 ms recoveries
    # (docs/realtime.md); since its first stage (the predicted rotation alone) ends the search
    # when it passes, the held cube's failed fits cost about 7 ms more instead of about 36.
    # 0: the search from scratch only, as the simulated task runs
    eye_local_starts: int = 12
    # of the local search's turned starts, how many go on from the coarse gates to the fine
    # ones (``TrackConfig.local_keep``; 0: all). Session 22: 4 made the turned stage 10.3 ms
    # instead of 18.4 on 9 rendered frames, each recovered either way, but alone it did not
    # bring a turned recovery within the age bound in six 60 s runs, and one fit in contact
    # went unrecovered (cause unknown), so it stayed 0. Since 2026-11-27 (session 25) 4, with
    # ``eye_local_merge``: on the 5 turned recoveries saved in real-time runs both together
    # give the same fits (within 0.2 mm) in 17-23 ms of eye instead of 29-34 on the quiet
    # CPU, and a frame nothing recovers is left to the prediction (``eye_defer_search``)
    # rather than searched (docs/realtime.md, "Deferring the search")
    eye_local_keep: int = 4
    # the local search's turned starts at the predicted centre only where it lies within this
    # fraction of the box size of the last fitted one (``TrackConfig.local_merge``; 0: both
    # centres). The held cube's centres were 0-8 mm apart on those frames
    eye_local_merge: float = 0.1
    # while the eye's filter runs, its search from scratch only after this many failed frames
    # in a row (``TrackConfig.defer_search``), for the run and its twin alike: the first is
    # left to the prediction. In 84 runs of 60 s before (sessions 22-24) that search never
    # found the cube while the filter ran, and each try cost 0.1-0.4 s of eye (every frame in
    # between dropped, the state-age bound missed), where the frames that failed came one at a
    # time (but for the runaway in depth, since recovered by ``depth_gate``). 0: every failed
    # frame searched (before 2026-11-27; the ablation). docs/realtime.md, "Deferring the search"
    eye_defer_search: int = 1
    # the eye's jitted fits and searches compiled with the tracker's small-kernel options
    # (``TrackConfig.cpu_small_kernels``: no YNNPACK fusions, single-threaded Eigen), for the run
    # and its twin alike; the same arithmetic to round-off. False: XLA's defaults (the ablation)
    eye_small_kernels: bool = False
    # the eye keeps up to this many frames whose tracked fit failed (the image and occluded
    # pixels it was given, the tracker's snapshot before the frame), written to the run folder
    # as eye_failed_frames.pkl for an offline replay (``workers.replay_failed_frames``); 0: none.
    # A diagnostic: each frame then costs a copy of the track (tens of us)
    eye_save_failed: int = 0
    # the eye's manoeuvre restart (``TrackConfig.maneuver_nis`` of the scene's tracker: a fit far
    # outside the filter's prediction restarts its velocity from that one fit), for the run and
    # its twin alike. Off by default: on frames without anti-aliasing the held cube's fit at
    # times flips to a tilted twin for a frame or two; the restart took the flip's jump for an
    # impact, the prediction ran away and the eye lost the cube (docs/realtime.md, "The eye's
    # CPU and the held cube"). True: the scene's tracker's restart
    eye_maneuver_restart: bool = False
    # multisample anti-aliasing of the rendered camera (MuJoCo's offsamples); None: the scene's
    # (4, as the simulated camera loop). 0 makes software rendering about 3x cheaper (13 -> 4 ms
    # at 320x240) at the price of aliased edges: a real camera costs the computer nothing, the
    # simulated one competes with the eye and the loop for the CPU. The simulated twin renders
    # alike (``CameraConfig.msaa``; before 2026-11-26 it kept the scene's 4 samples)
    camera_msaa: int | None = None
    # [m] grid spacing of the rendered planes (``CameraConfig.plane_grid_m``; the twin renders
    # alike); None: the scene's (0.01 m). scene.xml's floor at 0.01 m is 80,000 quads, about
    # 2/3 of a 640x480 software render; at 0.05 the render took 3.2 ms instead of 6.9 (one
    # core, the release frame) and its floor shading changed by at most a grey level for 99%
    # of the 2% of pixels that changed (docs/realtime.md, "The floor's render grid")
    camera_plane_grid_m: float | None = None
    # the rendered lights cast shadows; None: the scene's (the lab's do, the void's do not).
    # False makes the lab's software rendering 3x cheaper (30 -> 10 ms a 640x480 frame without
    # multisampling on the 2-core VM); the eye's calibration shots are rendered alike, the
    # simulated twin keeps the scene's shadows
    camera_shadows: bool | None = None
    # nice value of the camera and eye processes (-20..19; below 0 needs root): under normal
    # scheduling a lower value gives them a larger share of the CPU than other processes
    child_nice: int = 0
    # [s] how long the loop waits, before each release, for the eye's answer on the release
    # frame (its search from scratch, ~0.4 s on one core): the cube is held in view until the
    # eye has it, then released (the simulated camera loop's first estimate arrives 1 frame
    # latency after the release instead)
    acquire_timeout_s: float = 10.0
    # the same run in simulated time beside the real-time one: "auto" (the eye's source: the
    # MJX episode for truth, the simulated camera loop for camera; the ground-truth MJX episode
    # always), "truth" (MJX episode only), "none"
    twin: Literal["auto", "truth", "none"] = "auto"
    # the camera twin's eye latency (``CameraConfig.latency_s`` of the simulated camera loop):
    # "measured", the real-time eye's median latency in this run (exposure -> the tick that
    # first used the estimate; :func:`~hec_jax.realtime.runner.twin_camera_latency_s`), so
    # that the twin's controller acts on estimates as old as the run's; "configured", the
    # camera's own (1/30 s after the exposure's end by default: about 3x the real-time eye's on
    # the 2-core VM, docs/realtime.md, "Why the camera twin did not hold the cube")
    twin_latency: Literal["measured", "configured"] = "measured"
    startup_timeout_s: float = 600.0  # [s] for the camera and eye processes to be ready
    # while the loop runs (timed, pinned), the CPUs other than the loop's kept busy by one
    # process each at SCHED_IDLE (``clock.idle_filler``): "spin" a busy loop, "memory" a stream
    # through 256 MiB; the camera and the eye preempt it at once. None: they idle between
    # frames (docs/realtime.md, "The other CPU kept busy": not shown to help the loop)
    idle_filler: Literal["spin", "memory"] | None = None

    @property
    def pool_idle_applies(self) -> bool:
        """``pool_idle`` takes effect: set, timed, pinned and without real-time priority."""
        return self.pool_idle and self.timed and self.pin_cpus and not self.rt_priority

    def __post_init__(self):
        if self.duration_s is not None and not (
            math.isfinite(self.duration_s) and self.duration_s > 0
        ):
            raise ValueError(f"duration_s must be finite and > 0 or None, got {self.duration_s}")
        for name in ("spin_us", "lead_ms", "startup_timeout_s", "acquire_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"RealtimeConfig.{name} must be finite and >= 0, got {v}")
        if not (isinstance(self.rt_priority, int) and 0 <= self.rt_priority <= 99):
            raise ValueError(f"rt_priority must be an integer in 0..99, got {self.rt_priority}")
        if self.cpu_latency_us is not None and not (
            isinstance(self.cpu_latency_us, int) and 0 <= self.cpu_latency_us < 2**31
        ):
            raise ValueError(
                f"cpu_latency_us must be None or an integer >= 0, got {self.cpu_latency_us!r}"
            )
        for name in ("camera_priority", "eye_priority"):
            v = getattr(self, name)
            if not (isinstance(v, int) and 0 <= v <= 99):
                raise ValueError(f"RealtimeConfig.{name} must be an integer in 0..99, got {v}")
            if self.rt_priority and v >= self.rt_priority:
                raise ValueError(f"RealtimeConfig.{name} must be below rt_priority")
        if self.twin_latency not in ("measured", "configured"):
            raise ValueError(
                f"twin_latency must be 'measured' or 'configured', got {self.twin_latency!r}"
            )
        if self.idle_filler not in (None, "spin", "memory"):
            raise ValueError(
                f"idle_filler must be None, 'spin' or 'memory', got {self.idle_filler!r}"
            )
        if not isinstance(self.eye_on_control_cpu, bool):
            raise ValueError(f"eye_on_control_cpu must be a bool, got {self.eye_on_control_cpu!r}")
        if self.eye_on_control_cpu and (not self.pin_cpus or self.rt_priority <= 0):
            raise ValueError(
                "eye_on_control_cpu needs pin_cpus and rt_priority > 0: without real-time "
                "priority the eye would compete with the control loop for its CPU"
            )
        if not isinstance(self.pool_idle, bool):
            raise ValueError(f"pool_idle must be a bool, got {self.pool_idle!r}")
        if self.pool_rescue_us is not None and not (
            isinstance(self.pool_rescue_us, (int, float))
            and not isinstance(self.pool_rescue_us, bool)
            and math.isfinite(self.pool_rescue_us)
            and self.pool_rescue_us > 0
        ):
            raise ValueError(f"pool_rescue_us must be None or > 0, got {self.pool_rescue_us!r}")
        if not (
            isinstance(self.pool_rescue_poll_us, (int, float))
            and not isinstance(self.pool_rescue_poll_us, bool)
            and math.isfinite(self.pool_rescue_poll_us)
            and self.pool_rescue_poll_us > 0
        ):
            raise ValueError(f"pool_rescue_poll_us must be > 0, got {self.pool_rescue_poll_us!r}")
        if not (isinstance(self.child_nice, int) and -20 <= self.child_nice <= 19):
            raise ValueError(f"child_nice must be an integer in -20..19, got {self.child_nice}")
        if self.camera_msaa is not None and not (
            isinstance(self.camera_msaa, int) and 0 <= self.camera_msaa <= 16
        ):
            raise ValueError(
                f"camera_msaa must be None or an integer in 0..16, got {self.camera_msaa}"
            )
        if not (isinstance(self.eye_local_starts, int) and 0 <= self.eye_local_starts <= 256):
            raise ValueError(
                f"eye_local_starts must be an integer in 0..256, got {self.eye_local_starts!r}"
            )
        if not (isinstance(self.eye_save_failed, int) and 0 <= self.eye_save_failed <= 1000):
            raise ValueError(
                f"eye_save_failed must be an integer in 0..1000, got {self.eye_save_failed!r}"
            )
        if not (isinstance(self.eye_local_keep, int) and 0 <= self.eye_local_keep <= 256):
            raise ValueError(
                f"eye_local_keep must be an integer in 0..256, got {self.eye_local_keep!r}"
            )
        if not (isinstance(self.eye_local_merge, (int, float)) and 0 <= self.eye_local_merge <= 10):
            raise ValueError(
                f"eye_local_merge must be a number in 0..10, got {self.eye_local_merge!r}"
            )
        if not (isinstance(self.eye_defer_search, int) and 0 <= self.eye_defer_search <= 100):
            raise ValueError(
                f"eye_defer_search must be an integer in 0..100, got {self.eye_defer_search!r}"
            )
        if self.camera_plane_grid_m is not None and not (
            isinstance(self.camera_plane_grid_m, (int, float))
            and 0 < self.camera_plane_grid_m < math.inf
        ):
            raise ValueError(
                "camera_plane_grid_m must be None or a number > 0 [m], "
                f"got {self.camera_plane_grid_m!r}"
            )
        if not isinstance(self.eye_small_kernels, bool):
            raise ValueError(f"eye_small_kernels must be a bool, got {self.eye_small_kernels!r}")
        if self.condition not in ("plain", "frozen", "learned"):
            raise ValueError(f"condition must be plain, frozen or learned, got {self.condition!r}")
