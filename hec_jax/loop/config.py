"""Configuration of the closed task loop: frozen dataclasses, defined once, and named presets.

Every hyperparameter of an experiment has one definition and one default here (or in the config
of the part that uses it: ``LearnerConfig``, ``ControllerConfig``, ``PendulumConfig``,
``TrackConfig``); the scripts' command-line flags are derived from these dataclasses
(:mod:`hec_jax.cli`), and a preset is a function returning a filled-in :class:`ExperimentConfig`
whose docstring argues each choice. Constants of the plant (time step, torque limits) are read
from the MuJoCo model, never repeated here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import tyro

from hec_jax.cli import require
from hec_jax.control import ControllerConfig
from hec_jax.geometry import PaperEyeConfig, TrackConfig
from hec_jax.geometry.track import UNSEEN_SCENES
from hec_jax.mjx_scene import X_HOME, PendulumConfig
from hec_jax.nets import LearnerConfig, NetConfig

# The object's state: the simulator's ("truth"), or camera frames through the box tracker
# ("camera", ``geometry.BoxTracker``) or through the paper's two-frame method ("paper",
# ``geometry.PaperEye``: Eqs. 1-38 on a pair of parallel cube edges in consecutive frames).
EyeSource = Literal["truth", "camera", "paper"]
EYE_SOURCES = ("truth", "camera", "paper")
TOUCH_MEMORY_ACROSS = ("follow_hand", "hand_velocity")  # TaskConfig.touch_memory_across


def _positive(obj, *names: str, allow_zero: bool = False) -> None:
    for name in names:
        v = getattr(obj, name)
        ok = v is not None and math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
        if not ok:
            rel = ">= 0" if allow_zero else "> 0"
            raise ValueError(f"{type(obj).__name__}.{name} must be finite and {rel}, got {v}")


@dataclass(frozen=True)
class TargetImpedance:
    """The target impedance of Eq. 40 per task axis (x, z): the hand's apparent mass, damping and
    stiffness. The controller realises it; the learner's output bound U (Eq. 51) and the Eq. 49
    margins are taken against it. Values: docs/paper_readings.md, parameter values.
    """

    m_e: tuple[float, float] = (1.0, 1.0)  # M_e [kg]
    b_e: tuple[float, float] = (40.0, 40.0)  # B_e [N s/m]
    k_e: tuple[float, float] = (400.0, 400.0)  # K_e [N/m]

    def __post_init__(self):
        for name in ("m_e", "b_e", "k_e"):
            v = getattr(self, name)
            if len(v) != 2 or not all(math.isfinite(x) and x > 0 for x in v):
                raise ValueError(f"TargetImpedance.{name} must be 2 finite values > 0, got {v}")


@dataclass(frozen=True)
class TaskConfig:
    """One task (catching or hitting: ``learner.task``) in the simulated world.

    Durations are in seconds; the loop turns them into control steps with the model's time step.
    """

    learner: LearnerConfig = field(default_factory=LearnerConfig)
    impedance: TargetImpedance = field(default_factory=TargetImpedance)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    pendulum: PendulumConfig = field(default_factory=PendulumConfig)
    # X_d (x, z) [m]: where the hand waits; None: the point named by ``home``.
    x_home: tuple[float, float] | None = X_HOME
    # With x_home None: "hold_point", where gravity presses a caught cube on the hand with
    # learner.f_desired (:func:`hec_jax.loop.policy.hold_point`); "rest_touch", where the hand
    # just touches the hanging cube at rest (:func:`hec_jax.loop.policy.rest_touch_point`).
    home: Literal["hold_point", "rest_touch"] = "hold_point"
    swings: int = 10  # releases from the same state; the learner's weights carry over
    swing_s: float = 3.0  # [s] one swing
    final_s: float = 0.0  # [s] one continuous run after the swings (weights carried over); 0: none
    settle_s: float = 0.5  # [s] the settle force is the mean |F_int| over a swing's last settle_s
    contact_threshold: float = 1e-3  # [N] |F_int| above this counts as contact
    # Camera runs, after a contact while the eye's estimate predates it (``TouchMemory``): across
    # the last contact normal the object keeps its offset from the hand ("follow_hand": position,
    # velocity and acceleration follow the hand's), or moves on at the hand's velocity at the last
    # touch ("hand_velocity", the rule until 2026-12-03; ``object_state.touch_object_state`` says
    # why it changed). Along the normal both extrapolate the hand's velocity at the last touch.
    touch_memory_across: Literal["follow_hand", "hand_velocity"] = "follow_hand"
    # [s] time constant of a first-order low-pass on the object's acceleration X_o'' when the
    # object state is the simulator's (camera runs take the eye filter's estimate); 0: X_o'' is
    # the 1 kHz backward difference of X_o' (impact-dominated in contact, see VIN_NOTE). The
    # hand's X_e'' is never filtered (dX_o'' = X_o'' - X_e'' keeps its impact spike).
    object_accel_tau_s: float = 0.0
    # Hand-cube contact (the scene's hand_cube pair), written into the MJX model's pair_solref
    # (timeconst [s], dampratio) / pair_solimp; None keeps scene.xml's (0.005 s, 1: critically
    # damped, restitution about 0). scene.xml itself is never changed.
    contact_solref: tuple[float, float] | None = None
    contact_solimp: tuple[float, float, float, float, float] | None = None
    # Constraint solver caps (opt.iterations / opt.ls_iterations); None keeps scene.xml's
    # (100 / 50). A vmapped batch iterates until its slowest member converges.
    solver_iterations: int | None = None
    ls_iterations: int | None = None
    # opt.solver ("newton" / "cg") and opt.jacobian ("dense" / "sparse"); None keeps scene.xml's
    # (Newton, dense). cg + sparse has no batched Cholesky (fastest on a GPU) and reaches Newton's
    # solution with at least 8 iterations.
    solver: Literal["newton", "cg"] | None = None
    jacobian: Literal["dense", "sparse"] | None = None

    def __post_init__(self):
        if not (isinstance(self.swings, int) and self.swings >= 1):
            raise ValueError(f"TaskConfig.swings must be an integer >= 1, got {self.swings}")
        _positive(self, "swing_s", "settle_s", "contact_threshold")
        _positive(self, "final_s", "object_accel_tau_s", allow_zero=True)
        if self.settle_s > self.swing_s:
            raise ValueError(f"settle_s ({self.settle_s}) must not exceed swing_s ({self.swing_s})")
        if self.home not in ("hold_point", "rest_touch"):
            raise ValueError(f"home must be 'hold_point' or 'rest_touch', got {self.home!r}")
        if self.touch_memory_across not in TOUCH_MEMORY_ACROSS:
            raise ValueError(
                f"touch_memory_across must be one of {TOUCH_MEMORY_ACROSS}, "
                f"got {self.touch_memory_across!r}"
            )
        if self.x_home is not None and (
            len(self.x_home) != 2 or not all(math.isfinite(v) for v in self.x_home)
        ):
            raise ValueError(f"x_home must be 2 finite values [m], got {self.x_home}")
        if self.contact_solref is not None and not all(
            math.isfinite(v) and v > 0 for v in self.contact_solref
        ):
            raise ValueError(f"contact_solref must be 2 values > 0, got {self.contact_solref}")
        for name in ("solver_iterations", "ls_iterations"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, int) and v >= 1):
                raise ValueError(f"TaskConfig.{name} must be an integer >= 1 or None, got {v}")


# camera defects are modelled in the simulated-time loop only (hec_jax.loop.camera_loop)
REALTIME_DEFECTS = (
    "camera defects (--noise-grey, --blur-renders, ...) are simulated-time only, not --realtime"
)
# so is a trigger phase: the real-time camera's frames start at each release
REALTIME_FRAME_OFFSET = (
    "--frame-offset-s and --frame-offset-random are simulated-time only: the real-time camera's "
    "frames start at each release"
)


@dataclass(frozen=True)
class CameraDefects:
    """What makes the loop's camera imperfect, applied at the NumPy boundary
    (:mod:`hec_jax.loop.camera_loop`); every defect is off by default (the perfect rendered camera).

    The renderer always uses the true camera; the eye (tracker, self-mask, overlay) uses the
    perturbed intrinsics. Noise and jitter are drawn from two generators (one each, so that one
    can be turned off without changing the other's draws) seeded by ``defect_seed``, the seed's
    index in the batch and the swing: the same settings give the same frames.
    """

    noise_grey: float = 0.0  # sensor noise: Gaussian, standard deviation [grey levels of 255]
    defocus_px: float = 0.0  # Gaussian blur sigma [px] (defocus; under 0.05 px: none)
    # motion blur: renders averaged over the exposure (``exposure_s``, at the midpoints of equal
    # sub-intervals on the 1 ms grid); 1: one render at mid-exposure (no blur)
    blur_renders: int = 1
    focal_error: float = 0.0  # the eye's fx, fy are the true ones times (1 + focal_error) [-]
    centre_error_px: float = 0.0  # the eye's cx, cy are the true ones + this [px]
    # the frame time stamps the controller gets are off by uniform(-jitter_s, jitter_s) [s]
    # (the exposure itself stays on the frame grid)
    jitter_s: float = 0.0
    defect_seed: int = 0  # seed of the noise and the jitter

    @classmethod
    def industrial(cls, defect_seed: int = 0) -> CameraDefects:
        """A plausible calibrated machine-vision camera (``--camera-model industrial``): a 1/2.9"
        global-shutter CMOS (e.g. Sony IMX273/IMX296 class, 3.45 um pixels) at 30 fps over USB3,
        software-triggered, with a fixed C-mount lens, calibrated with a checkerboard.

        * **Noise 2 grey levels**: at 8 bits and 0 dB gain one grey level is about 40 e-
          (saturation about 10 ke-); temporal dark noise is about 2.5 e- and the shot noise of a
          mid-grey pixel (5 ke-) 70 e-, i.e. about 1.8 grey levels: 2 with a little gain.
        * **Motion blur over the 4 ms exposure** (``CameraConfig.exposure_s``, 3 renders): indoor
          lab light at f/2.8 needs a few ms; the cube at up to about 1.5 m/s moves 6 mm (about
          2 px at 1.7 m) during it.
        * **Defocus 0.5 px**: a fixed-focus lens focused on the swing plane; the swing's depth
          range and the lens's MTF give a blur spot of about one pixel (sigma 0.5 px).
        * **Focal length 1% off, principal point 1.5 px off**: typical residual errors of a
          checkerboard calibration of such a camera (fx, fy to 0.5-1%; cx, cy to 1-2 px).
        * **Time-stamp jitter 1 ms**: a software-triggered USB3 camera stamped on the host: the
          trigger and transfer latency varies by about +-1 ms.

        Lens distortion and rolling shutter are not modelled (a global shutter has none).
        """
        return cls(
            noise_grey=2.0,
            defocus_px=0.5,
            blur_renders=3,
            focal_error=0.01,
            centre_error_px=1.5,
            jitter_s=0.001,
            defect_seed=defect_seed,
        )

    def __post_init__(self):
        require(self, "non_negative", "noise_grey", "defocus_px", "jitter_s")
        require(self, "count", "blur_renders")
        require(self, "seed", "defect_seed")
        if not (math.isfinite(self.focal_error) and abs(self.focal_error) < 0.5):
            raise ValueError(
                f"--focal-error: must be finite and in (-0.5, 0.5), got {self.focal_error!r}"
            )
        if not (math.isfinite(self.centre_error_px) and abs(self.centre_error_px) <= 100):
            raise ValueError(
                f"--centre-error-px: must be finite and within +-100 px, got {self.centre_error_px!r}"
            )


# the names of CameraDefects' fields (``CameraConfig.defects_given``)
DEFECT_FIELDS = tuple(f.name for f in dataclasses.fields(CameraDefects))


# The issue-24 checks of ``UNSEEN_SCENES`` that the loop's tracker takes in the lab scene
# (``min_region_fraction`` stays off: in the loop the moving arm is the largest blob)
LAB_CHECKS = (
    "colour_background",
    "foreground_edges",
    "min_foreground",
    "min_iou_acquire",
    "min_inner_support",
)


def scene_tracker(scene: str) -> TrackConfig:
    """The loop's box tracker for a scene (``CameraConfig.track`` left at None).

    Both are set for impacts on the hand: a failed fit is tried again from the last fitted
    position, and an innovation jump (chi-square 3 dof, p = 0.001) restarts the velocity.
    ``"void"``: nothing else (black background; the tracker of every void-scene number in the
    docs, tested against its record). ``"lab"``: plus ``UNSEEN_SCENES``' checks
    (:data:`LAB_CHECKS`: colour differences to the calibration shot, the moving blob's edges
    only, the fit confirmed by its silhouette and inner edges), which a background with clutter,
    shadows and edges needs: without them the lab's held cube lost 40-164 of 546 frames, with
    them none (``docs/eye_pipeline.md``). They stay off in the void scene, where they made the
    main job worse (``docs/eye_randomized.md``, last section).
    """
    loop = TrackConfig(maneuver_nis=16.3, stop_hypothesis=True)
    if scene == "void":
        return loop
    if scene == "lab":
        return dataclasses.replace(loop, **{k: getattr(UNSEEN_SCENES, k) for k in LAB_CHECKS})
    raise ValueError(f"--scene: must be 'void' or 'lab', got {scene!r}")


@dataclass(frozen=True)
class CameraConfig:
    """Timing and resolution of the eye in the loop (``--eye camera`` and ``--eye paper``).

    The defaults are a plausible lab (issue 24, point 5): the ``"lab"`` scene seen from an
    oblique pose, through ``CameraDefects.industrial()``, with :func:`scene_tracker`'s tracker.
    :meth:`void_perfect` is the camera of every number recorded before 2026-11-26 (scene.xml's
    black void along the swing plane's normal, no defects) and ``--realtime``'s default
    (real time has no defects; it renders the lab too, on a GPU renderer).
    """

    fps: float = 30.0  # frame rate [1/s]; frames fall on whole control steps (33 ms at 30 fps)
    latency_s: float = 1.0 / 30.0  # end of exposure -> estimate at the controller [s]
    # the frame shows the state at mid-exposure [s] (motion blur: ``defects.blur_renders``)
    exposure_s: float = 0.004
    # [s] the camera's trigger phase against each release: the first frame's exposure ends this
    # long after it, the others 1/fps apart (rounded to whole control steps; 0 <= offset <
    # 1/fps). A free-running camera meets each release at its own phase, and the learned
    # vertical damping depends strongly on it (docs/realtime.md, session 80). Simulated time
    # only: the real-time camera's frames start at each release (0)
    frame_offset_s: float = 0.0
    # a free-running camera: each release meets it at a phase drawn uniformly from the frame
    # period's control steps (the generator: ``defects.defect_seed`` and the swing), in place of
    # ``frame_offset_s``. Every swing keeps the frame count of the latest phase, so a swing whose
    # phase fits one more frame before its end goes without it
    # (``camera_loop.frame_steps``). Simulated time only
    frame_offset_random: bool = False
    width: int = 640  # [px]
    height: int = 480  # [px]
    # no shadows/reflections (3x faster software rendering); the lab scene keeps its shadows
    fast_render: bool = True
    # what the camera sees: "void", scene.xml (black background, the camera along the swing
    # plane's normal), or "lab", a room around it with shadows and an oblique camera
    # (``hec_jax.mjx_scene.lab``; rendering only, the simulated model is the same)
    scene: Literal["void", "lab"] = "lab"
    # "perfect": the defects are the flags below (all off by default); "industrial":
    # ``CameraDefects.industrial()``'s values for every defect flag left at its default (a flag
    # given with a non-default value keeps it; --defect-seed is kept): to turn one defect off,
    # use "perfect" with the others given
    camera_model: Literal["perfect", "industrial"] = "industrial"
    # Frames without a valid fit after which the filter's extrapolation is no longer used: the
    # object counts as unseen (F_o = 0, no learning) until the eye finds it again.
    max_coast_frames: int = 2
    # The robot masks its own links out of each frame (projected from its joint angles and the
    # calibrated camera), widened by this margin [m]; None: no mask. Without it the hand's outline
    # next to a held cube is taken for a cube edge (measured: 10-16 mm jumps at rest).
    self_mask_margin_m: float | None = 0.005
    inpaint_hand: bool = True  # the hand's part of that mask is inpainted, not painted black
    # The mask leaves the box tracker's predicted box silhouette alone where the box is nearer
    # the camera than the hand (``camera_loop.front_object_mask``): the mask ignores occlusion
    # and, from an oblique camera, inpaints part of a cube held in front of the hand. Off by
    # default (the main job's setting; in the void scene the two are at the same depth)
    occlusion_aware_mask: bool = False
    # The eye is told which pixels the mask replaced (painted or inpainted): its fits' coverage
    # check counts only the cube's edge length outside them (``geometry.track.associate``). An
    # edge under the hand is then unobservable, not missing: without it, fits of the held cube
    # failed that check (``docs/realtime.md``). False: as before 2026-11-26 (the ablation).
    mask_aware_coverage: bool = True
    # After the hand last felt the object, estimates from frames exposed less than this many frame
    # periods later are not used (the eye's filter needs post-impact frames for the new velocity);
    # the object is extrapolated from the last touch (``object_state.TouchMemory``) until the
    # first post-guard estimate can have arrived, plus the coasting allowance.
    touch_guard_frames: float = 2.0
    # Multisample anti-aliasing of the rendered frames (MuJoCo's ``offsamples``); None: the
    # scene's (4). 0 is what the real-time camera renders on a software renderer
    # (``RealtimeConfig.camera_msaa``); set it here to render the simulated loop alike.
    msaa: int | None = None
    # [m] grid spacing of the rendered planes (the floor): MuJoCo draws a plane as a grid of
    # quads, scene.xml's floor at 0.01 m (80,000 quads, about 2/3 of a software render of a
    # 640x480 frame); rendering only (``mjx_scene.with_plane_grid``). None: the scene's. The
    # real-time camera renders alike (``RealtimeConfig.camera_plane_grid_m``)
    plane_grid_m: float | None = None
    # The eye's box tracker; None: the scene's (:func:`scene_tracker`, read through
    # :attr:`tracker`, which is what runs and what the run folder records)
    track: Annotated[TrackConfig | None, tyro.conf.Suppress] = None
    # The paper's eye (``--eye paper``): face edges, Eqs. 1-38 between consecutive frames, the
    # composed pose and its filter (``geometry.paper_eye``; defaults argued there).
    paper: Annotated[PaperEyeConfig, tyro.conf.Suppress] = field(default_factory=PaperEyeConfig)
    # sensor noise, blur, intrinsics error, time-stamp jitter: the flags (all off by default);
    # what runs is :attr:`applied_defects` (camera_model "industrial", the default: the flags
    # left unset take its values)
    defects: CameraDefects = field(default_factory=CameraDefects)
    # the ``defects`` fields set explicitly: with camera_model "industrial" each keeps its value
    # even where that is the perfect camera's, so ``--focal-error 0`` turns that one defect off
    # (without it a flag at the perfect camera's value reads as unset). The task scripts fill it
    # from the flags on their command line (``hec_jax.loop.cli.parse_task``)
    defects_given: Annotated[tuple[str, ...], tyro.conf.Suppress] = ()

    @classmethod
    def void_perfect(cls, **overrides) -> CameraConfig:
        """scene.xml's black void seen along the swing plane's normal by a perfect camera: the
        set-up of every camera number recorded before 2026-11-26, and ``--realtime``'s default
        (defects are simulated-time only; software rendering keeps 30 fps in the void only).
        """
        return cls(**{"scene": "void", "camera_model": "perfect", **overrides})

    @property
    def tracker(self) -> TrackConfig:
        """The box tracker that runs: ``track``, or the scene's (:func:`scene_tracker`)."""
        return scene_tracker(self.scene) if self.track is None else self.track

    @property
    def applied_defects(self) -> CameraDefects:
        """The defects the loop applies: ``defects`` (the flags) with ``camera_model``'s values
        for the flags left at their defaults and not named in ``defects_given``
        (``"perfect"``: the flags as given).
        """
        if self.camera_model == "industrial":
            return _industrial_over(self.defects, self.defects_given)
        return self.defects

    def realtime_refused(self) -> str | None:
        """Why the real-time loop cannot run this camera (its defects or its trigger phase are
        simulated-time only), or None.
        """
        if self.applied_defects != CameraDefects():
            return REALTIME_DEFECTS
        if self.frame_offset_s != 0 or self.frame_offset_random:
            return REALTIME_FRAME_OFFSET
        return None

    def resolved(self) -> CameraConfig:
        """This camera with ``track`` and ``defects`` filled in (:attr:`tracker`,
        :attr:`applied_defects`): what a run folder records; runs the same.
        """
        return dataclasses.replace(self, track=self.tracker, defects=self.applied_defects)

    def __post_init__(self):
        if self.scene not in ("void", "lab"):
            raise ValueError(f"--scene: must be 'void' or 'lab', got {self.scene!r}")
        if self.camera_model not in ("perfect", "industrial"):
            raise ValueError(
                f"--camera-model: must be 'perfect' or 'industrial', got {self.camera_model!r}"
            )
        _positive(self, "fps", "width", "height")
        _positive(
            self, "latency_s", "exposure_s", "touch_guard_frames", "frame_offset_s", allow_zero=True
        )
        if not isinstance(self.frame_offset_random, bool):
            raise ValueError(
                f"frame_offset_random must be a bool, got {self.frame_offset_random!r}"
            )
        if self.frame_offset_random and self.frame_offset_s != 0:
            raise ValueError(
                "--frame-offset-random draws each swing's phase: leave --frame-offset-s at 0"
            )
        if not self.frame_offset_s < 1.0 / self.fps:
            raise ValueError(
                f"--frame-offset-s: the first frame's offset must be below the frame period "
                f"({1.0 / self.fps:.4g} s), got {self.frame_offset_s!r}"
            )
        if not (isinstance(self.max_coast_frames, int) and self.max_coast_frames >= 0):
            raise ValueError(
                f"max_coast_frames must be an integer >= 0, got {self.max_coast_frames}"
            )
        if self.msaa is not None and not (isinstance(self.msaa, int) and 0 <= self.msaa <= 16):
            raise ValueError(f"--msaa: must be None or an integer in 0..16, got {self.msaa!r}")
        if self.plane_grid_m is not None and not (
            isinstance(self.plane_grid_m, (int, float)) and 0 < self.plane_grid_m < math.inf
        ):
            raise ValueError(
                f"--plane-grid-m: must be None or a number > 0 [m], got {self.plane_grid_m!r}"
            )
        unknown = set(self.defects_given) - set(DEFECT_FIELDS)
        if unknown:
            raise ValueError(
                f"defects_given: not fields of CameraDefects: {sorted(unknown)} "
                f"(fields: {', '.join(DEFECT_FIELDS)})"
            )
        applied = self.applied_defects
        if not applied.jitter_s < 0.5 / self.fps:
            raise ValueError(
                f"--jitter-s: must be below half the frame period ({0.5 / self.fps:.4g} s), "
                f"got {applied.jitter_s!r}"
            )
        if self.exposure_s > 1.0 / self.fps:
            raise ValueError(
                f"--exposure-s: an exposure cannot outlast the frame period "
                f"({1.0 / self.fps:.4g} s), got {self.exposure_s!r}"
            )
        if applied.blur_renders > 1 and self.exposure_s <= 0:
            raise ValueError("--blur-renders above 1 needs --exposure-s > 0")


def _industrial_over(given: CameraDefects, keep: tuple[str, ...] = ()) -> CameraDefects:
    """``CameraDefects.industrial()`` with every field of ``given`` that differs from its
    default or is named in ``keep``.
    """
    base = CameraDefects.industrial()
    off = CameraDefects()
    return dataclasses.replace(
        base,
        **{
            name: getattr(given, name)
            for name in DEFECT_FIELDS
            if name in keep or getattr(given, name) != getattr(off, name)
        },
    )


@dataclass(frozen=True)
class ExperimentConfig:
    """A task run under the three conditions (plain, frozen, learned) for a batch of seeds."""

    task: TaskConfig = field(default_factory=TaskConfig)
    # the object's state: the simulator's, or camera frames via the box tracker ("camera") or the
    # paper's two-frame method on parallel edges ("paper")
    eye: EyeSource = "truth"
    camera: CameraConfig = field(default_factory=CameraConfig)
    seed: int = 0  # PRNG seed of the network initialisations
    seeds: int = 5  # network initialisations, run side by side (vmap)

    def __post_init__(self):
        if not (isinstance(self.seeds, int) and self.seeds >= 1):
            raise ValueError(f"seeds must be an integer >= 1, got {self.seeds}")
        if self.eye not in EYE_SOURCES:
            raise ValueError(f"eye must be one of {', '.join(EYE_SOURCES)}, got {self.eye!r}")
        # jax.random.PRNGKey keeps the low 32 bits with 64-bit JAX off: 2**32 + 5 would be 5
        if (
            isinstance(self.seed, bool)
            or not isinstance(self.seed, int)
            or not (0 <= self.seed < 2**32)
        ):
            raise ValueError(f"seed must be an integer in [0, 2**32), got {self.seed}")
        if self.task.learner.task == "hitting" and not self.task.final_s > 0:
            raise ValueError(
                "the hitting experiment counts its hits in the continuous run: final_s must be "
                f"> 0, got {self.task.final_s}"
            )


# ---------------------------------------------------------------------------------------------
# Named presets


def _learner(task: str, f_desired: float, mu: float, eta_vin: float) -> LearnerConfig:
    """The learner settings both tasks share (R_b, rates, nominal contact stiffness).

    R_b = 0.085 m: below the contact distance (hand radius + half cube = 0.09 m), as the gain
    functions need (``hec_jax.nets.learner``). eta = 0.3 for the VSN and VVN. k_c = 1e5 N/m: the
    nominal stiffness of scene.xml's contact (timeconst 0.005 s) at the cube's mass scale.
    """
    return LearnerConfig(
        task=task,
        radius=0.25,
        r_b=0.085,
        eta=(0.3, 0.3, eta_vin),
        mu=mu,
        f_desired=f_desired,
        contact_stiffness=1e5,
    )


# Why the task presets leave the VIN (M_o) untrained (eta of the VIN = 0; it keeps its initial
# output, about -0.05 kg): M_o multiplies dX_o'' (Eq. 47), which the controller forms as a 1 ms
# backward difference of the measured velocities. In contact that signal is the contact impulse
# itself (hundreds of m/s^2 over a few ms), so the VIN's gradient (Eq. 53) and its force
# M_o dX_o'' are driven by the impacts rather than by the relative motion the network is meant to
# shape (the paper's accelerations come from a 30 Hz camera, far smoother). Measured with eta 0.3:
# catching chatters on the hand for one seed of two (48 contact episodes); hitting unaffected.
VIN_NOTE = "eta_m = 0: dX_o'' is a 1 kHz backward difference, impact-dominated in contact"


def catching(**overrides) -> ExperimentConfig:
    """Catching (Sec. 6.2, Eqs. 59-62, Fig. 6) as set up in this project (our choices; the paper
    gives no numbers), with ``overrides`` of :class:`ExperimentConfig`'s top-level fields.

    * **Where the hand waits** (``x_home=None``: the hold point). A held cube is pressed on the
      hand only by gravity, so a steady force F_cd needs the hand between the approaching cube and
      its rest position, where the pendulum is displaced by theta_cd with
      F_cd L_c = (m_c L_c + m_rod L/2) g sin(theta_cd). X_d is that hold point minus the hand's own
      spring deflection F_cd / K_e, so a caught cube at rest presses with F_cd: plain impedance
      settles at F_cd by construction. The hinge sits at x = 0.55 m (scene.xml: 0.35 m) because
      the hold point of the default pendulum is out of the arm's reach there.
    * **F_cd = 2 N**: the smallest round force whose *hold window* L_c sin(theta_cd) (17.4 cm)
      exceeds the up to 0.16 m the virtual spring pushes the hand during a soft catch; with 1 N
      the cube is carried past its rest position and strikes again (measured).
    * With the hand at the hold point the released cube starts 0.23 m from it, inside the virtual
      sphere (r = 0.25 m): t_c is the first sample and X_r'(t_c) = 0, so the gain alpha of Eq. 60
      acts only through its zero below R_b (an issue of its own: the cube does not enter from
      outside as the paper intends).
    * The hand-cube contact keeps scene.xml's pair (solref 0.005 s, dampratio 1). mu = 1e-3.
      10 swings of 3 s; the VIN is not trained (``VIN_NOTE``).
    """
    task = TaskConfig(
        learner=_learner("catching", f_desired=2.0, mu=1e-3, eta_vin=0.0),
        pendulum=PendulumConfig(hinge_x=0.55),
        x_home=None,
        swings=10,
        swing_s=3.0,
        settle_s=0.5,
    )
    return ExperimentConfig(**{"task": task, "eye": "camera", **overrides})


def hitting(**overrides) -> ExperimentConfig:
    """Hitting (Sec. 6.3, Eqs. 63-66, Fig. 7) as set up in this project, with ``overrides`` of
    :class:`ExperimentConfig`'s top-level fields.

    Protocol: 10 training swings of 2 s from the same release (the world restarts each swing, the
    weights carry over), then one continuous run of 12 s (the pendulum never reset) with learning
    going on; hits are counted in that run. The hand waits at ``X_HOME`` (0.65, 0.60) m.

    * **Hitting pad** (contact_solref = (0.025 s, 0.2)): scene.xml's hand-cube pair is critically
      damped (restitution about 0), so a struck cube only leaves with the hand's own velocity.
      The pad keeps that contact's stiffness (MuJoCo: natural frequency 1 / (timeconst dampratio),
      the product 0.005 s kept) and lowers the damping ratio to 0.2: restitution
      exp(-pi 0.2 / sqrt(1 - 0.2^2)) = 0.53, a wooden block on a rubber-faced paddle.
    * mu = 1e-5: at 1e-3 the impact term (k_c = 1e5) dominates the first hit and drives K_o to
      +180 N/m, which ends all further hits (measured). F_hd = 5 N. VIN not trained (``VIN_NOTE``).
    """
    task = TaskConfig(
        learner=_learner("hitting", f_desired=5.0, mu=1e-5, eta_vin=0.0),
        x_home=X_HOME,
        contact_solref=(0.025, 0.2),
        swings=10,
        swing_s=2.0,
        final_s=12.0,
    )
    return ExperimentConfig(**{"task": task, "eye": "camera", **overrides})


def sweep_catching() -> TaskConfig:
    """The task of each run of the catching sweep (``hec_jax.loop.sweep``): 6 swings of 1.5 s,
    the hand at ``X_HOME``, F_cd = 1 N, mu = 1e-3, all three networks learning (eta 0.3 each); the
    pendulum's fields are the sweep's grid.
    """
    return TaskConfig(
        learner=_learner("catching", f_desired=1.0, mu=1e-3, eta_vin=0.3),
        x_home=X_HOME,
        swings=6,
        swing_s=1.5,
        settle_s=0.3,
    )


# The paper presets' shared choices (``catching_paper``, ``hitting_paper``): one hand, one contact.
# Hand-cube contact: MuJoCo solref (timeconst 0.01 s, dampratio 0.3): a wooden cube on a hand
# whose force-sensor plate has a thin rubber face. Restitution exp(-pi 0.3 / sqrt(1 - 0.3^2)) =
# 0.37 (wood on hard rubber: 0.3-0.5); contact stiffness about m_c / (timeconst dampratio)^2 =
# 0.7 / 0.003^2 = 7.8e4 N/m, which is the learner's nominal k_c; the impact lasts about
# pi timeconst dampratio ... pi timeconst (10-30 ms), as a rubber-faced plate gives.
PAPER_CONTACT_SOLREF = (0.01, 0.3)
PAPER_CONTACT_STIFFNESS = 7.8e4  # [N/m]
# The hinge sits at x = 0.55 m (scene.xml 0.35 m): the hand waits where it touches the hanging
# cube, (0.64, 0.60) m, inside the arm's reach with room to move; at x = 0.35 that point lies at
# 93% of the arm's reach and a held cube pushes it out of reach.
PAPER_HINGE_X = 0.55


def _paper_learner(task: str, f_desired: float, mu: float) -> LearnerConfig:
    """The paper presets' learner: all three networks learn (eta 0.3 each), neutral initial
    networks (O = 0), R_b = 0.085 m (below the contact distance 0.09 m), r = 0.25 m.
    """
    return LearnerConfig(
        task=task,
        radius=0.25,
        r_b=0.085,
        eta=(0.3, 0.3, 0.3),
        mu=mu,
        f_desired=f_desired,
        contact_stiffness=PAPER_CONTACT_STIFFNESS,
        net=NetConfig(neutral_init=True),
    )


def _paper_task(task: str, f_desired: float, mu: float, **timing) -> TaskConfig:
    """What both paper presets share: the hand at the rest-touch point, the hinge at
    ``PAPER_HINGE_X``, one contact model, the camera-rate object acceleration, 10 training
    swings; ``timing``: the task's swing_s / settle_s / final_s.
    """
    return TaskConfig(
        learner=_paper_learner(task, f_desired=f_desired, mu=mu),
        pendulum=PendulumConfig(hinge_x=PAPER_HINGE_X),
        x_home=None,
        home="rest_touch",
        contact_solref=PAPER_CONTACT_SOLREF,
        object_accel_tau_s=1.0 / 30.0,
        swings=10,
        **timing,
    )


def catching_paper(**overrides) -> ExperimentConfig:
    """Catching as close to Sec. 6.2 as the paper allows (the ``paper`` protocol:
    :mod:`hec_jax.loop.protocol` draws each training swing's and each held-out evaluation's
    pendulum from :class:`~hec_jax.loop.protocol.ConditionRange`), with ``overrides`` of
    :class:`ExperimentConfig`'s top-level fields.

    * **Home point** (``x_home=None`` with ``home="rest_touch"``): the hand waits where it just
      touches the hanging cube at the pendulum's rest, (0.64, 0.60) m; chosen without reference
      to F_cd: a caught cube at rest there presses with 0 N under plain impedance, so reaching
      F_cd is the controller's and the networks' job.
    * **The cube enters the sphere from outside**: released at -0.6 ... -0.4 rad it starts
      0.34-0.48 m from the hand (r = 0.25 m), so t_c falls during the swing and X_r'(t_c) is the
      approach velocity that alpha (Eq. 62) shapes.
    * **One contact model** for both tasks (``PAPER_CONTACT_SOLREF``, restitution 0.37).
    * **All three networks learn** (eta 0.3 each). The object's acceleration X_o'' is low-passed
      with a 1/30 s time constant (``object_accel_tau_s``), as smooth as the paper's 30 Hz
      camera estimate; camera runs use the eye filter's estimate. The hand's X_e'' is not: it
      is the 1 kHz backward difference, as a robot's own sensing would give it. So the VIN's
      relative acceleration dX_o'' = X_o'' - X_e'' still spikes at an impact: on one frozen
      swing of this preset (docs/experiments.md, 2026-12-04) its peak in contact was 175 m/s^2
      (29 m/s^2 for the low-passed X_o'' alone; 0.37 m/s^2 median inside the sphere before
      contact). Low-passing X_e'' too was not tried.
    * **Neutral initial networks** (``NetConfig.neutral_init``): O = 0 at the start, so the frozen
      baseline is plain impedance plus the small random output weights.
    * F_cd = 2 N (the catching preset's value; the paper gives none), mu = 1e-3 as there.
      Swings of 3 s; settle window 0.5 s.
    """
    task = _paper_task("catching", f_desired=2.0, mu=1e-3, swing_s=3.0, settle_s=0.5)
    return ExperimentConfig(**{"task": task, "eye": "truth", **overrides})


def hitting_paper(**overrides) -> ExperimentConfig:
    """Hitting as close to Sec. 6.3 as the paper allows, with the same hand, home point, contact
    model and learner as :func:`catching_paper` (F_hd = 5 N, mu = 1e-5 as the hitting preset);
    training swings of 2 s with the pendulum drawn per swing, then the evaluation runs are
    continuous (``final_s`` = 8 s) on held-out conditions, learning on, hits counted.
    """
    task = _paper_task("hitting", f_desired=5.0, mu=1e-5, swing_s=2.0, final_s=8.0)
    return ExperimentConfig(**{"task": task, "eye": "truth", **overrides})


PRESETS = {
    "catching": catching,
    "hitting": hitting,
    "catching_paper": catching_paper,
    "hitting_paper": hitting_paper,
}


def replace(config, **changes):
    """``dataclasses.replace`` for nested configs: ``replace(exp, swings=3, mu=2e-3)`` sets the
    (unique) field of that name wherever it lives in the config tree.

    Raises:
        ValueError: no field, or more than one, has that name.
    """
    for name, value in changes.items():
        config = _replace_one(config, name, value)
    return config


def _paths(config, name, prefix=()):
    out = []
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        if f.name == name:
            out.append((*prefix, f.name))
        elif dataclasses.is_dataclass(v):
            out += _paths(v, name, (*prefix, f.name))
    return out


def _replace_one(config, name, value):
    paths = _paths(config, name)
    if len(paths) != 1:
        where = ", ".join(".".join(p) for p in paths) or "nowhere"
        raise ValueError(f"field {name!r} must occur once in {type(config).__name__}: {where}")

    def set_at(obj, path):
        if len(path) == 1:
            return dataclasses.replace(obj, **{path[0]: value})
        return dataclasses.replace(obj, **{path[0]: set_at(getattr(obj, path[0]), path[1:])})

    return set_at(config, paths[0])
