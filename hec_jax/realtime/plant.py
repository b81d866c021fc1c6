"""The plant seen by the real-time loop: a robot driver's interface, and MuJoCo C behind it.

:class:`Plant` is the seam where a robot driver replaces the simulator: read the joint state, the
end-point force and the time; write joint torques; a :class:`Camera` returns the newest frame with
the time stamp of its exposure. :class:`ArmModel` is the controller's own model of the arm: from
the measured joint state it computes, with MuJoCo C functions, what the impedance law needs
(M(theta), h(theta, theta'), J, J' theta', X_e of Eqs. 39-44); no MJX on the control path.

:class:`MujocoPlant` implements :class:`Plant` with MuJoCo C physics on the wall clock: physics
step j (plant time j dt -> (j + 1) dt) uses the torque computed from sample j if it was written
before the step's deadline, wall time (j + 1) dt after the episode's origin; otherwise the motors
hold the last torque they were given (zero-order hold, as a robot's servo drives do), the step is
counted as missed and the late torque takes effect from the next step. Steps whose deadline
passes with no controller call at all are integrated with the held torque when the controller
next reads (``skipped``). A sample is never released before its wall time: the runner waits for
tick j before it reads. The step sequence is :func:`hec_jax.mjx_scene.rollout_c`'s (the simulated
loop's): position and velocity stages at the state, torques, constraint solve, semi-implicit
Euler; the force measurement is the previous step's contact force on the hand.

With a camera, every physics step's state (time, qpos) goes to a shared board, and a separate
process (:func:`hec_jax.realtime.workers.camera_main`) renders a frame whenever the plant time
reaches the next frame's mid-exposure (the simulated camera loop's frame times: every
``steps_per_frame`` steps, half the exposure before each exposure's end), stamped with the plant
time of the state it shows; frames that rendering could not start on time are counted. The
process keeps the software renderer off the control loop's core and out of its GIL.
"""

from __future__ import annotations

import os
from typing import NamedTuple, Protocol

import mujoco
import numpy as np

from hec_jax.loop.camera_loop import mid_exposure_steps, steps_per_frame
from hec_jax.loop.config import CameraConfig, TaskConfig
from hec_jax.mjx_scene import (
    TASK_AXES,
    SceneIds,
    hand_contact_force_c,
    make_data_c,
    mj_model_with_conditions,
    scene_ids,
    set_solver_options,
)
from hec_jax.mjx_scene.lab import scene_model
from hec_jax.mjx_scene.render import render_model_like, with_plane_grid
from hec_jax.mjx_scene.sim import held_at
from hec_jax.realtime.clock import Clock, monotonic_s
from hec_jax.realtime.shared import _CTX, Board, FrameRing, Images, wait_for

_AX = np.array(TASK_AXES)


class PlantSample(NamedTuple):
    """One sample of the plant, as a robot driver gives it.

    Attributes:
        index: the sample's step number in the episode (plant time = index dt).
        t: [s] plant time of the sample.
        q: [rad] (3,) arm joint angles theta.
        qd: [rad/s] (3,) joint velocities theta'.
        f_int: [N] (3,) force ON the hand, world frame (the force sensor; Eq. 39's F_int).
        x_o, xd_o: [m], [m/s] (2,) the object's true centre and velocity (task plane) where the
            plant has them (simulator, motion capture); None otherwise.
    """

    index: int
    t: float
    q: np.ndarray
    qd: np.ndarray
    f_int: np.ndarray
    x_o: np.ndarray | None = None
    xd_o: np.ndarray | None = None


class Frame(NamedTuple):
    """One camera frame.

    Attributes:
        image: (H, W, 3) uint8 RGB.
        index: frame number since the camera started.
        episode: the episode it belongs to.
        number: frame number within the episode (0 at the release).
        t_exposure: [s] plant time of the state it shows.
        t_wall_exposure: [s] monotonic wall time of that state.
        q_arm: [rad] (3,) the arm's joint angles at the exposure (for the robot's self-mask).
    """

    image: np.ndarray
    index: int
    episode: int
    number: int
    t_exposure: float
    t_wall_exposure: float
    q_arm: np.ndarray


class Camera(Protocol):
    """A camera of the plant, read by the eye (usually in its own process)."""

    def latest(self, after: int = -1) -> Frame | None:
        """The newest frame if its index is > ``after``, else None (never blocks)."""
        ...

    def background(self) -> np.ndarray:
        """(H, W, 3) uint8: the static scene without the object (a calibration shot)."""
        ...


class Plant(Protocol):
    """A robot (or its simulation) at the control rate.

    Attributes:
        dt: [s] the control period (one sample per period).
    """

    dt: float

    def begin_episode(self, steps: int) -> None:
        """Puts the world in the release state (the simulator resets; a robot waits for the
        operator's release); ``steps``: the episode's length in samples.
        """
        ...

    def start(self, clock: Clock) -> None:
        """Sample 0 of the episode is at ``clock`` time 0."""
        ...

    def read(self) -> PlantSample:
        """The current sample (blocks for nothing: the caller waits for its tick)."""
        ...

    def write(self, tau: np.ndarray) -> float:
        """Joint torques [N m] (3,) for the sample last read; returns the clock time [s] at
        which the plant took them (the sample's deadline is compared with it).
        """
        ...


def plant_model(task: TaskConfig) -> mujoco.MjModel:
    """The C model of the task's world: the pendulum's conditions compiled into scene.xml
    (:func:`~hec_jax.mjx_scene.mj_model_with_conditions`), the solver options and the hand-cube
    contact of the task (as :func:`hec_jax.loop.policy.build_loop` puts them into MJX).
    """
    m = mj_model_with_conditions(task.pendulum.conditions())
    set_solver_options(m, task.solver_iterations, task.ls_iterations, task.solver, task.jacobian)
    if task.contact_solref is not None:
        m.pair_solref[:] = np.asarray(task.contact_solref)
    if task.contact_solimp is not None:
        m.pair_solimp[:] = np.asarray(task.contact_solimp)
    return m


def camera_model(
    task: TaskConfig, cam: CameraConfig, shadows: bool | None = None
) -> tuple[mujoco.MjModel, bool]:
    """The C model the real-time camera renders and the eye is calibrated on, and whether its
    lights cast shadows: :func:`plant_model` itself in the ``"void"`` scene (no shadows); in
    the ``"lab"`` the room around it (:func:`hec_jax.mjx_scene.lab.scene_model`, the plant's
    geometry copied onto scene.xml's rows as the simulated camera loop does), shadows on.
    ``shadows`` given: that instead of the scene's. Its planes drawn with ``cam.plane_grid_m``
    (:func:`~hec_jax.mjx_scene.with_plane_grid`; None: the scene's), as the simulated loop.
    """
    m = plant_model(task)
    if cam.scene != "void":
        m = render_model_like(scene_model(cam.scene), m)
    m = with_plane_grid(m, cam.plane_grid_m)
    return m, (cam.scene != "void") if shadows is None else bool(shadows)


class ArmObs(NamedTuple):
    """The arm's part of the observation (NumPy, float64; task axes (x, z)).

    Attributes:
        M: [kg m^2] (3, 3) M(theta), armature included.
        h: [N m] (3,) h(theta, theta') of Eq. 39 (bias minus passive forces).
        J: [m/rad] (2, 3) hand Jacobian; jdot_qdot: [m/s^2] (2,) J' theta'.
        x_e, xd_e: [m], [m/s] (2,) hand centre and velocity.
    """

    M: np.ndarray
    h: np.ndarray
    J: np.ndarray
    jdot_qdot: np.ndarray
    x_e: np.ndarray
    xd_e: np.ndarray


def empty_arm_obs() -> ArmObs:
    """An :class:`ArmObs` of new, uninitialised arrays (for :meth:`ArmModel.observe`'s ``out``)."""
    return ArmObs(
        np.empty((3, 3)), np.empty(3), np.empty((2, 3)), np.empty(2), np.empty(2), np.empty(2)
    )


class ArmModel:
    """The controller's model of the arm: Eqs. 39-44's M, h, J, J' theta' and X_e from a joint
    state, by MuJoCo C (mj_fwdPosition / mj_fwdVelocity, mj_fullM, mj_jacSite, mj_jacDot) on its
    own ``MjData``. The arm is its own kinematic tree, so the pendulum's state (unknown to a
    robot) does not enter; the numbers are those of :func:`hec_jax.mjx_scene.c_quantities` on
    the plant's data.

    Args:
        m: a C model holding the arm (e.g. :func:`plant_model`).
        ids: its scene ids.
    """

    def __init__(self, m: mujoco.MjModel, ids: SceneIds):
        self.m, self.ids = m, ids
        self.d = mujoco.MjData(m)
        self._qpos, self._dof = np.array(ids.arm_qpos), np.array(ids.arm_dof)
        self._dof_dof = np.ix_(self._dof, self._dof)  # M(theta): the arm's rows and columns
        self._hand = (ids.hand_site, _AX)
        self._M = np.zeros((m.nv, m.nv))
        self._jac = np.zeros((3, m.nv))
        self._jacdot = np.zeros((3, m.nv))

    def observe(self, q: np.ndarray, qd: np.ndarray, out: ArmObs | None = None) -> ArmObs:
        """The arm's observation at joint angles ``q`` [rad] and velocities ``qd`` [rad/s],
        written into ``out``'s arrays (e.g. views of the controller's observation vector: no
        allocation, about half the NumPy calls per tick) or new ones (None); returns it.
        """
        m, d, ids = self.m, self.d, self.ids
        out = empty_arm_obs() if out is None else out
        d.qpos[self._qpos] = q
        d.qvel[self._dof] = qd
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_fwdVelocity(m, d)
        mujoco.mj_fullM(m, d, self._M)
        mujoco.mj_jacSite(m, d, self._jac, None, ids.hand_site)
        mujoco.mj_jacDot(m, d, self._jacdot, None, d.site_xpos[ids.hand_site], ids.hand_body)
        qd = np.asarray(qd, np.float64)
        out.M[...] = self._M[self._dof_dof]
        np.subtract(d.qfrc_bias[self._dof], d.qfrc_passive[self._dof], out=out.h)
        # the products on operands indexed as observe_c does (its J is column-major): BLAS sums
        # in another order for another layout (or alignment) of an operand, 1 ulp apart
        J = self._jac[_AX][:, self._dof]
        out.J[...] = J
        out.jdot_qdot[...] = self._jacdot[_AX][:, self._dof] @ qd
        out.x_e[...] = d.site_xpos[self._hand]
        out.xd_e[...] = J @ qd
        return out


# the board's fields besides qpos: simulated time [s], the step, the episode, the monotonic wall
# time of the write [s] and the plant's clock time then [s] (NaN before the episode's clock
# runs): a reader tells steps on time from a burst of catch-up steps by them
STATE_FIELDS = {"t": (), "step": (), "episode": (), "t_wall": (), "t_clock": ()}


class PlantCounts(NamedTuple):
    """What happened to one episode's physics steps (they add up to ``steps``).

    Attributes:
        steps: physics steps integrated.
        fresh: steps integrated with the torque computed from their own sample in time.
        late: steps whose torque came after their deadline (the held torque was used).
        skipped: steps integrated with the held torque with no controller call at all.
    """

    steps: int
    fresh: int
    late: int
    skipped: int


class MujocoPlant:
    """:class:`Plant` on MuJoCo C physics stepping on the wall clock (module docstring).

    Args:
        task: the task (world, contact, solver).
        q_home: [rad] (3,) the arm's posture at each release.
        camera: the camera's rate and resolution; None: no camera (no render process).
        object_truth: samples carry the cube's true state (``--eye truth``).
        camera_priority: SCHED_FIFO priority of the camera process (0: normal scheduling).
        camera_nice: nice value of the camera process.
        camera_msaa: the renderer's multisample anti-aliasing (None: the scene's).
        camera_shadows: the lights cast shadows (None: the scene's; the lab's do).
    """

    def __init__(
        self,
        task: TaskConfig,
        q_home,
        camera: CameraConfig | None = None,
        object_truth: bool = True,
        camera_priority: int = 0,
        camera_nice: int = 0,
        camera_msaa: int | None = None,
        camera_shadows: bool | None = None,
    ):
        self.task = task
        self.m = plant_model(task)
        self.ids = scene_ids(self.m)
        self.dt = self.ids.timestep
        self.conditions = task.pendulum.conditions()
        self.q_home = np.asarray(q_home, np.float64)
        self.object_truth = object_truth
        # qpos at the release (the camera's calibration shots, the eye's warm-up frame)
        self.q_release = make_data_c(self.m, self.ids, self.conditions, self.q_home).qpos.copy()
        self.episode = -1
        self.d: mujoco.MjData | None = None
        self.clock: Clock | None = None
        self.board = Board({**STATE_FIELDS, "qpos": (self.m.nq,)})
        self.camera_config = camera
        self._camera_proc = None
        self._jac_cube = np.zeros((3, self.m.nv))
        self._arm_qpos, self._arm_dof = np.array(self.ids.arm_qpos), np.array(self.ids.arm_dof)
        self._arrival = float(self.conditions.arrival_phase)
        self.frames: FrameRing | None = None
        self.calibration: Images | None = None
        if camera is not None:
            self._start_camera(camera, camera_priority, camera_nice, camera_msaa, camera_shadows)

    # -- camera process ------------------------------------------------------------------------
    def _start_camera(
        self, cam: CameraConfig, priority: int, nice: int, msaa, shadows: bool | None
    ) -> None:
        from hec_jax.realtime import workers

        meta = {
            "episode": (),
            "number": (),
            "t_exposure": (),
            "t_wall_exposure": (),
            "t_wall_done": (),
            "q_arm": (3,),
        }
        self.frames = FrameRing(cam.height, cam.width, meta)
        self.calibration = Images(2, cam.height, cam.width)
        self._stop = _CTX.Event()
        self._camera_log = _CTX.Queue()
        q0 = self.q_release
        period = steps_per_frame(cam, self.dt)
        with _child_env():
            self._camera_proc = _CTX.Process(
                target=workers.camera_main,
                args=(self.task, cam, period, q0, self.board, self.frames, self.calibration),
                kwargs=dict(
                    stop=self._stop,
                    log_queue=self._camera_log,
                    priority=priority,
                    nice=nice,
                    msaa=msaa,
                    shadows=shadows,
                    dt=self.dt,
                    # the state at mid-exposure, as the simulated camera loop shows it
                    exposure_back=mid_exposure_steps(cam, self.dt),
                ),
                daemon=True,
                name="hec-camera",
            )
            self._camera_proc.start()

    def wait_camera(self, timeout_s: float = 120.0) -> None:
        """Waits until the camera has its calibration shots (background, release frame).

        Raises:
            TimeoutError: not within ``timeout_s``.
            RuntimeError: the camera process died.
        """
        if self.calibration is None:
            return

        def ok():
            if not self._camera_proc.is_alive():
                raise RuntimeError("the camera process died while starting")
            return self.calibration.ready(1)

        wait_for(ok, timeout_s, 0.01, "the camera process")

    def camera(self) -> SharedCamera:
        """The :class:`Camera` of this plant (hand it to the eye's process)."""
        if self.frames is None:
            raise ValueError("this plant has no camera")
        return SharedCamera(self.frames, self.calibration)

    def close(self) -> dict | None:
        """Stops the camera process; returns its log (None without a camera)."""
        if self._camera_proc is None:
            return None
        self._stop.set()
        log = None
        try:
            log = self._camera_log.get(timeout=30)
        except Exception:  # noqa: BLE001 - a dead camera leaves no log; the caller reports that
            log = None
        self._camera_proc.join(timeout=10)
        if self._camera_proc.is_alive():
            self._camera_proc.terminate()
        self._camera_proc = None
        return log

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- plant ---------------------------------------------------------------------------------
    def begin_episode(self, steps: int) -> None:
        """The world at the release (arm at ``q_home`` at rest), a new episode number and an
        empty log of ``steps`` physics steps (:meth:`episode_log`).
        """
        self.d = make_data_c(self.m, self.ids, self.conditions, self.q_home)
        m = self.m
        self._log = {
            "t": np.zeros(steps),
            "qpos": np.zeros((steps, m.nq)),
            "qvel": np.zeros((steps, m.nv)),
            "f_contact": np.zeros((steps, 3)),
            "ctrl": np.zeros((steps, m.nu)),
            "kind": np.zeros(steps, np.int8),
            "t_wall_done": np.zeros(steps),
        }
        self.episode += 1
        self.clock = None  # until :meth:`start`: the board's t_clock is NaN
        self.j = 0  # the step to integrate next (= the sample the controller may read)
        self._staged = False
        self._f_contact = np.zeros(3)
        self._u = np.zeros(self.m.nu)  # the torque the motors hold [N m]
        self._counts = [0, 0, 0]  # fresh, late, skipped
        self._publish()

    def start(self, clock: Clock) -> None:
        """Sample 0 is at ``clock`` time 0 (deadline of step j: (j + 1) dt)."""
        self.clock = clock

    @property
    def counts(self) -> PlantCounts:
        """The episode's step counts so far."""
        fresh, late, skipped = self._counts
        return PlantCounts(self.j, fresh, late, skipped)

    def _stage(self) -> None:
        """Position and velocity stages at the state (the pendulum held until its release)."""
        if self._staged:
            return
        m, d, ids = self.m, self.d, self.ids
        if held_at(d.time, self._arrival, self.dt):
            d.qpos[ids.pend_qpos] = float(self.conditions.release_angle)
            d.qvel[ids.pend_dof] = float(self.conditions.release_speed)
        d.xfrc_applied[:] = 0.0
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_fwdVelocity(m, d)
        self._staged = True

    def _integrate(self, u: np.ndarray, kind: int) -> None:
        """Step j under torques ``u``: constraint solve, contact force, Euler; publishes."""
        self._stage()
        m, d = self.m, self.d
        d.ctrl[:] = u
        mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, 1)
        self._f_contact = hand_contact_force_c(m, d, self.ids)
        j, log = self.j, self._log
        if j < len(log["t"]):
            log["t"][j] = d.time
            log["qpos"][j] = d.qpos
            log["qvel"][j] = d.qvel
            log["f_contact"][j] = self._f_contact
            log["ctrl"][j] = u
            log["kind"][j] = kind
            log["t_wall_done"][j] = self.clock.now()
        mujoco.mj_Euler(m, d)
        self._staged = False
        self._counts[kind] += 1
        self.j += 1
        self._publish()
        # the next sample's stages now, after the torques were taken, rather than in the next
        # read: the simulator's work leaves the tick's latency (a robot's read costs a few us).
        # The same calls in the same order as a lazy stage: the same numbers.
        self._stage()

    def _publish(self) -> None:
        if self._camera_proc is not None:
            d = self.d
            t_clock = self.clock.now() if self.clock is not None else np.nan
            self.board.write(
                t=d.time,
                step=self.j,
                episode=self.episode,
                t_wall=monotonic_s(),
                t_clock=t_clock,
                qpos=d.qpos,
            )

    def _catch_up(self) -> None:
        """Integrates, with the held torque, every step of the episode whose deadline has
        passed (none past its end: a late last write ends it there).
        """
        now = self.clock.now()
        self._late_row = self.j
        while now >= (self.j + 1) * self.dt and self.j < len(self._log["t"]):
            self._integrate(self._u, 2)

    def read(self) -> PlantSample:
        """The current sample (after integrating the steps whose deadline has passed)."""
        self._catch_up()
        self._stage()
        d, ids = self.d, self.ids
        x_o = xd_o = None
        if self.object_truth:
            mujoco.mj_jacSite(self.m, d, self._jac_cube, None, ids.cube_site)
            x_o = d.site_xpos[ids.cube_site][_AX]
            xd_o = (self._jac_cube @ d.qvel)[_AX]
        return PlantSample(
            index=self.j,
            t=float(d.time),
            q=d.qpos[self._arm_qpos],
            qd=d.qvel[self._arm_dof],
            f_int=self._f_contact.copy(),
            x_o=x_o,
            xd_o=xd_o,
        )

    def write(self, tau) -> float:
        """Torques [N m] (3,) for the current sample: applied to its step if before the step's
        deadline, else held from the next step on (the step keeps the previous torque). Returns
        the clock time [s] at which they were taken.
        """
        tau = np.asarray(tau, np.float64)
        now = self.clock.now()
        if now < (self.j + 1) * self.dt:
            self._integrate(tau, 0)
        else:
            self._catch_up()  # the sample's own step (and any later ones): the held torque
            self._counts[1] += 1
            self._counts[2] -= 1  # the first of them was this sample's step: late, not skipped
            self._log["kind"][self._late_row] = 1
        self._u = tau
        return now

    # -- what the simulator knows besides the samples ----------------------------------------
    def episode_log(self) -> dict[str, np.ndarray]:
        """Per physics step of the episode so far: ``t`` [s], ``qpos``, ``qvel`` (the state the
        step started from), ``f_contact`` [N] (3,) its contact force on the hand (world),
        ``ctrl`` [N m] the torque applied, ``kind`` (0 fresh, 1 late, 2 skipped) and
        ``t_wall_done`` [s] when it was integrated (clock time).
        """
        n = min(self.j, len(self._log["t"]))
        return {k: v[:n].copy() for k, v in self._log.items()}


class SharedCamera:
    """:class:`Camera` reading a :class:`MujocoPlant`'s frames from shared memory (any process).

    Args:
        frames: the ring the camera process writes.
        calibration: its calibration shots (0: background, 1: the release frame).
    """

    def __init__(self, frames: FrameRing, calibration: Images):
        self.frames, self.calibration = frames, calibration

    def latest(self, after: int = -1) -> Frame | None:
        """The newest frame if its index is > ``after``, else None."""
        got = self.frames.get(after)
        if got is None:
            return None
        image, meta = got
        return Frame(
            image=image,
            index=int(meta["index"]),
            episode=int(meta["episode"]),
            number=int(meta["number"]),
            t_exposure=float(meta["t_exposure"]),
            t_wall_exposure=float(meta["t_wall_exposure"]),
            q_arm=meta["q_arm"].copy(),
        )

    def background(self) -> np.ndarray:
        """The background shot (pendulum hidden)."""
        return self.calibration.get(0)

    def release_frame(self) -> np.ndarray:
        """A frame of the release state (the eye compiles its tracker on it before the run)."""
        return self.calibration.get(1)


class _child_env:
    """Environment of the child processes while they start (spawn copies it): one software
    rendering thread, single-threaded Eigen in XLA, one OpenMP and one OpenCV thread, so each
    child keeps to one core. Each ``XLA_FLAGS`` token must be a ``--`` flag XLA knows (it skips
    other tokens silently and stops at an unknown flag).
    """

    SETTINGS = {
        "LP_NUM_THREADS": "1",
        "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
        "OMP_NUM_THREADS": "1",
        "OPENCV_FOR_THREADS_NUM": "1",
    }

    def __enter__(self):
        self._old = {k: os.environ.get(k) for k in self.SETTINGS}
        os.environ.update(self.SETTINGS)

    def __exit__(self, *exc):
        for k, v in self._old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
