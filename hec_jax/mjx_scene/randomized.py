"""Randomized rendered scenes of a swinging cube for the eye (issue 24; NumPy/MuJoCo C boundary).

:func:`draw_scene` draws a :class:`RandomScene` from a seed: camera viewpoint (elevation, azimuth
from the swing plane's normal, distance, aim offset, fovy), cube edge, its look (plain, wood-like
texture, low contrast against the wall behind), lighting (direction, intensity, ambient, shadows),
a room with clutter (boxes, shelves, posters: straight edges), the pendulum (rod length, release
angle) and the camera's imperfections applied after rendering (sensor noise, exposure gain, blur).
:func:`scene_mjcf` writes it as MJCF (with the texture images as assets) and
:func:`render_random_sequence` simulates the swing with MuJoCo C and renders it with the true cube
state in the camera frame (pinhole convention of :mod:`hec_jax.geometry.camera`).

World frame: z up; the pendulum's hinge axis is world y, so the swing plane is x-z and its normal
is y; the camera sits on the -y side (azimuth 0 looks along +y).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import mujoco
import numpy as np

from hec_jax.mjx_scene.camera import camera_intrinsics, camera_pose_world
from hec_jax.mjx_scene.lab import look_at_xyaxes, orbit_position
from hec_jax.mjx_scene.render import RenderedSequence, body_in_camera, sampled_motion, sensor

HINGE_HEIGHT = 1.6  # [m] above the floor


@dataclass(frozen=True)
class RandomSceneRanges:
    """The ranges scenes are drawn from (uniform unless said otherwise).

    Attributes:
        elevation_deg: camera elevation above the horizontal through the swing's lowest point [deg].
        azimuth_deg: largest |azimuth| of the camera from the swing plane's normal [deg].
        distance_m: camera distance to the swing's lowest point [m].
        edge_m: cube edge [m].
        rod_m: rod length, hinge to the cube's top face [m].
        release_rad: release angle of the pendulum [rad] (sign drawn too).
        fovy_deg: vertical field of view [deg].
        aim_px: largest offset of the image centre from the swing's lowest point, in image
            fractions [-].
        noise_sigma: sensor noise standard deviation [grey levels of 255].
        blur_px: Gaussian blur sigma (defocus / exposure) [px].
        motion_blur: probability of a motion-blurred sequence (exposure of ``exposure_s``).
        exposure_s: exposure time of a motion-blurred frame [s].
        gain: exposure gain on the rendered image [-].
    """

    elevation_deg: tuple[float, float] = (-10.0, 60.0)
    azimuth_deg: float = 70.0
    distance_m: tuple[float, float] = (0.6, 2.5)
    edge_m: tuple[float, float] = (0.05, 0.15)
    rod_m: tuple[float, float] = (0.3, 0.8)
    release_rad: tuple[float, float] = (0.1, 0.6)
    fovy_deg: tuple[float, float] = (40.0, 60.0)
    aim_px: float = 0.15
    noise_sigma: tuple[float, float] = (0.0, 4.0)
    blur_px: tuple[float, float] = (0.0, 0.8)
    motion_blur: float = 0.25
    exposure_s: tuple[float, float] = (0.002, 0.008)
    gain: tuple[float, float] = (0.75, 1.25)


@dataclass(frozen=True)
class RandomScene:
    """One drawn scene (hashable; everything :func:`scene_mjcf` and the post-render step need).

    Attributes:
        seed: the seed it was drawn from.
        elevation_deg, azimuth_deg, distance_m, fovy_deg: camera viewpoint.
        aim: (2,) aim offset in image fractions (x right, y up) [-].
        edge_m: cube edge [m]; rod_m: rod length [m]; release_rad: release angle [rad].
        look: "plain", "wood" or "low_contrast".
        cube_rgb: (3,) cube colour (mean colour of the wood texture) in [0, 1].
        wall_rgb, floor_rgb: (3,) colours in [0, 1]; floor_checker: a checker floor.
        light_dir: (3,) direction of the main light (world, pointing down) [-].
        light_diffuse, ambient: intensities [0, 1]; shadows: the main light casts shadows.
        clutter: tuple of boxes (cx, cy, cz, hx, hy, hz, yaw, r, g, b) [m, rad, 0-1].
        noise_sigma, blur_px, gain: post-render sensor noise [grey levels], blur [px], gain [-].
        exposure_s: exposure time [s] (0: no motion blur).
    """

    seed: int
    elevation_deg: float
    azimuth_deg: float
    distance_m: float
    fovy_deg: float
    aim: tuple[float, float]
    edge_m: float
    rod_m: float
    release_rad: float
    look: str
    cube_rgb: tuple[float, float, float]
    wall_rgb: tuple[float, float, float]
    floor_rgb: tuple[float, float, float]
    floor_checker: bool
    light_dir: tuple[float, float, float]
    light_diffuse: float
    ambient: float
    shadows: bool
    clutter: tuple[tuple[float, ...], ...]
    noise_sigma: float
    blur_px: float
    gain: float
    exposure_s: float


def _rgb(rng, lo=0.05, hi=0.95) -> tuple[float, float, float]:
    return tuple(float(x) for x in rng.uniform(lo, hi, 3))


def draw_scene(seed: int, ranges: RandomSceneRanges = RandomSceneRanges()) -> RandomScene:
    """A scene drawn from ``seed`` (``np.random.default_rng(seed)``) over ``ranges``."""
    rng = np.random.default_rng(seed)
    u = lambda r: float(rng.uniform(*r))  # noqa: E731
    elevation, distance, fovy = u(ranges.elevation_deg), u(ranges.distance_m), u(ranges.fovy_deg)
    azimuth = float(rng.uniform(-ranges.azimuth_deg, ranges.azimuth_deg))
    edge, rod = u(ranges.edge_m), u(ranges.rod_m)
    # the swing should mostly stay in view: its half-width at most ~0.8 of the half view
    half_view = distance * np.tan(np.deg2rad(fovy) / 2)
    arm = rod + edge / 2
    max_release = float(np.arcsin(min(1.0, 0.8 * half_view / arm)))
    release = min(u(ranges.release_rad), max(max_release, ranges.release_rad[0]))
    release *= float(rng.choice([-1.0, 1.0]))
    look = str(rng.choice(["plain", "wood", "low_contrast"], p=[0.4, 0.35, 0.25]))
    wall = _rgb(rng, 0.1, 0.9)
    if look == "low_contrast":
        cube = tuple(float(np.clip(c + rng.uniform(-0.08, 0.08), 0, 1)) for c in wall)
    elif look == "wood":
        cube = (
            float(rng.uniform(0.5, 0.8)),
            float(rng.uniform(0.3, 0.5)),
            float(rng.uniform(0.1, 0.25)),
        )
    else:
        cube = _rgb(rng)
    floor = _rgb(rng, 0.2, 0.9)
    if look == "low_contrast":  # the floor too, as it is behind the cube from high views
        floor = tuple(float(np.clip(c + rng.uniform(-0.1, 0.1), 0, 1)) for c in wall)
    az = np.deg2rad(rng.uniform(0, 360))
    el = np.deg2rad(rng.uniform(25, 85))
    light_dir = (float(np.cos(az) * np.cos(el)), float(np.sin(az) * np.cos(el)), -float(np.sin(el)))
    # clutter: boxes behind the swing (as seen from the camera) and on the floor to its sides
    clutter = []
    for _ in range(int(rng.integers(4, 12))):
        h = rng.uniform(0.03, 0.3, 3)
        back = rng.uniform(0.4, 2.5)  # beyond the swing plane, along the view direction
        side = rng.uniform(-2.0, 2.0)
        zc = rng.choice([h[2], rng.uniform(0.2, 2.2)])  # on the floor or on a shelf/wall
        clutter.append(
            (
                float(side),
                float(back),
                float(zc),
                *map(float, h),
                float(rng.uniform(0, np.pi)),
                *_rgb(rng),
            )
        )
    exposure = u(ranges.exposure_s) if rng.uniform() < ranges.motion_blur else 0.0
    return RandomScene(
        seed=int(seed),
        elevation_deg=elevation,
        azimuth_deg=azimuth,
        distance_m=distance,
        fovy_deg=fovy,
        aim=tuple(float(x) for x in rng.uniform(-ranges.aim_px, ranges.aim_px, 2)),
        edge_m=edge,
        rod_m=rod,
        release_rad=float(release),
        look=look,
        cube_rgb=cube,
        wall_rgb=wall,
        floor_rgb=floor,
        floor_checker=bool(rng.uniform() < 0.5),
        light_dir=light_dir,
        light_diffuse=float(rng.uniform(0.3, 0.9)),
        ambient=float(rng.uniform(0.1, 0.4)),
        shadows=bool(rng.uniform() < 0.5),
        clutter=tuple(clutter),
        noise_sigma=u(ranges.noise_sigma),
        blur_px=u(ranges.blur_px),
        gain=u(ranges.gain),
        exposure_s=float(exposure),
    )


def _wood_png(seed: int, rgb, size: int = 256) -> bytes:
    """A wood-like grain texture (PNG bytes): rings along one axis, distorted by low noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    warp = cv2.GaussianBlur(rng.normal(0, 1, (size, size)).astype(np.float32), (0, 0), 12) * 12
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.uniform(6, 14) * y + 0.15 * warp + 0.3 * x))
    shade = 0.75 + 0.35 * rings**3 + 0.05 * rng.normal(0, 1, (size, size))
    img = np.clip(np.asarray(rgb)[None, None, :] * shade[..., None], 0, 1)
    ok, buf = cv2.imencode(".png", (255 * img[..., ::-1]).astype(np.uint8))
    assert ok
    return buf.tobytes()


def _look_at_xyaxes(pos: np.ndarray, target: np.ndarray) -> str:
    return " ".join(f"{v:.9f}" for v in look_at_xyaxes(pos, target))


GRAVITY_M_S2 = 9.81  # the scene's gravity (``scene_mjcf``'s option)
ROD_MASS_KG, CUBE_MASS_KG = 0.05, 0.5  # the pendulum's masses (``scene_mjcf``'s geoms)


def max_swing_speed_m_s(ranges: RandomSceneRanges = RandomSceneRanges()) -> float:
    """An upper bound on the cube centre's speed in any scene drawn from ``ranges`` [m/s].

    Energy: released at rest from angle theta, the pendulum (a thin rod of length l and a cube
    of edge e whose centre is L = l + e/2 from the hinge) turns at most at
    w^2 = 2 g (1 - cos theta) (m_c L + m_r l / 2) / I, I = m_c (L^2 + e^2 / 6) + m_r l^2 / 3
    about the hinge (damping only lowers it), so the cube's centre moves at most at w L. Taken
    at the largest release angle and maximised over a 41 x 41 grid of rod lengths and cube
    edges in the ranges (the grid's largest; with 0.5% added for what lies between its points).
    Not the point-mass bound sqrt(2 g L (1 - cos theta)): the rod's mass sits nearer the hinge
    and makes the cube faster than that.
    """
    rod = np.linspace(*ranges.rod_m, 41)[:, None]
    edge = np.linspace(*ranges.edge_m, 41)[None, :]
    arm = rod + edge / 2
    inertia = CUBE_MASS_KG * (arm**2 + edge**2 / 6) + ROD_MASS_KG * rod**2 / 3
    moment = CUBE_MASS_KG * arm + ROD_MASS_KG * rod / 2
    lift = 1 - np.cos(ranges.release_rad[1])
    speed = arm * np.sqrt(2 * GRAVITY_M_S2 * lift * moment / inertia)
    return float(1.005 * speed.max())


def swing_bottom(scene: RandomScene) -> np.ndarray:
    """(3,) world position of the cube centre at the bottom of the swing [m]."""
    return np.array([0.0, 0.0, HINGE_HEIGHT - scene.rod_m - scene.edge_m / 2])


def camera_position(scene: RandomScene) -> np.ndarray:
    """(3,) world position of the camera [m]."""
    return orbit_position(
        swing_bottom(scene), scene.elevation_deg, scene.azimuth_deg, scene.distance_m
    )


def scene_mjcf(scene: RandomScene, width: int, height: int) -> tuple[str, dict[str, bytes]]:
    """(MJCF text, assets) of ``scene``: the pendulum (hinge ``hinge``, body ``cube``), the camera
    ``eye``, the lights, floor, walls and clutter.
    """
    f = lambda v: " ".join(f"{x:.6g}" for x in v)  # noqa: E731
    bottom = swing_bottom(scene)
    cam = camera_position(scene)
    # aim: shift the target so that the swing's bottom is off the image centre
    fwd = (bottom - cam) / np.linalg.norm(bottom - cam)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    half_h = scene.distance_m * np.tan(np.deg2rad(scene.fovy_deg) / 2)
    half_w = half_h * width / height
    target = bottom - scene.aim[0] * 2 * half_w * right - scene.aim[1] * 2 * half_h * up
    assets: dict[str, bytes] = {}
    half = scene.edge_m / 2
    if scene.look == "wood":
        assets["wood.png"] = _wood_png(scene.seed, scene.cube_rgb)
        cube_mat = '<material name="cube" texture="wood" texuniform="false"/>'
        cube_tex = '<texture name="wood" type="cube" file="wood.png"/>'
        cube_rgba = "1 1 1 1"
    else:
        cube_mat = f'<material name="cube" rgba="{f(scene.cube_rgb)} 1"/>'
        cube_tex = ""
        cube_rgba = f"{f(scene.cube_rgb)} 1"
    floor_tex = (
        f'<texture name="floor" type="2d" builtin="checker" width="256" height="256" '
        f'rgb1="{f(scene.floor_rgb)}" rgb2="{f(np.asarray(scene.floor_rgb) * 0.6)}"/>'
        '<material name="floor" texture="floor" texrepeat="8 8"/>'
        if scene.floor_checker
        else f'<material name="floor" rgba="{f(scene.floor_rgb)} 1"/>'
    )
    # the room: a wall behind the swing (beyond the farthest clutter), perpendicular to the view
    view = np.array([fwd[0], fwd[1], 0.0])
    view /= np.linalg.norm(view)
    side = np.array([-view[1], view[0], 0.0])
    wall_c = bottom + 3.2 * view
    wall_c[2] = 2.0
    wall_yaw = np.arctan2(view[1], view[0])
    boxes = []
    for i, (s, b, zc, hx, hy, hz, yaw, r, g, bl) in enumerate(scene.clutter):
        p = bottom + b * view + s * side
        p[2] = zc
        q = (np.cos((yaw + wall_yaw) / 2), 0, 0, np.sin((yaw + wall_yaw) / 2))
        boxes.append(
            f'<geom name="clutter{i}" type="box" pos="{f(p)}" size="{f((hx, hy, hz))}" '
            f'quat="{f(q)}" rgba="{r:.4g} {g:.4g} {bl:.4g} 1"/>'
        )
    qw = (np.cos(wall_yaw / 2), 0, 0, np.sin(wall_yaw / 2))
    light_pos = bottom - 3.0 * np.asarray(scene.light_dir)
    xml = f"""
<mujoco model="random_swing_{scene.seed}">
  <compiler angle="radian"/>
  <option timestep="0.001" gravity="0 0 {-GRAVITY_M_S2:.6g}"/>
  <visual>
    <global offwidth="{width}" offheight="{height}"/>
    <headlight ambient="{scene.ambient:.4g} {scene.ambient:.4g} {scene.ambient:.4g}"
               diffuse="0.15 0.15 0.15" specular="0 0 0"/>
    <quality shadowsize="1024"/>
  </visual>
  <asset>
    {cube_tex}
    {cube_mat}
    {floor_tex}
  </asset>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <light name="main" directional="true" pos="{f(light_pos)}" dir="{f(scene.light_dir)}"
           diffuse="{f([scene.light_diffuse] * 3)}" specular="0.1 0.1 0.1"
           castshadow="{"true" if scene.shadows else "false"}"/>
    <geom name="floor" type="plane" size="8 8 0.01" material="floor"/>
    <geom name="wall" type="box" pos="{f(wall_c)}" quat="{f(qw)}" size="0.02 6 2"
          rgba="{f(scene.wall_rgb)} 1"/>
    {"".join(boxes)}
    <camera name="eye" pos="{f(cam)}" xyaxes="{_look_at_xyaxes(cam, target)}"
            fovy="{scene.fovy_deg:.6g}"/>
    <body name="rod" pos="0 0 {HINGE_HEIGHT}">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.0005"/>
      <geom name="rod" type="cylinder" size="0.003 {scene.rod_m / 2:.6g}"
            pos="0 0 {-scene.rod_m / 2:.6g}" rgba="0.6 0.6 0.62 1" mass="{ROD_MASS_KG:.6g}" group="2"/>
      <body name="cube" pos="0 0 {-scene.rod_m - half:.6g}">
        <geom name="cube" type="box" size="{half:.6g} {half:.6g} {half:.6g}" material="cube"
              rgba="{cube_rgba}" mass="{CUBE_MASS_KG:.6g}" group="2"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
    return xml, assets


def post_process(frame: np.ndarray, scene: RandomScene, rng: np.random.Generator) -> np.ndarray:
    """The camera's imperfections on one rendered (H, W, 3) uint8 frame: exposure gain, Gaussian
    blur (defocus) and Gaussian sensor noise, clipped and rounded to uint8.
    """
    out = sensor(frame, rng, scene.noise_sigma, scene.blur_px, scene.gain)
    return out.copy() if out is frame else out


def render_random_sequence(
    scene: RandomScene,
    n_frames: int,
    fps: float = 30.0,
    width: int = 640,
    height: int = 480,
    exposure_samples: int = 3,
) -> tuple[RenderedSequence, np.ndarray]:
    """Simulate and render ``scene``: (sequence with the true cube state, background (H, W, 3)).

    The pendulum is released at rest from ``scene.release_rad``. A motion-blurred scene
    (``exposure_s > 0``) averages ``exposure_samples`` renders spread over the exposure ending at
    the frame time; its true state (position, rotation, velocity, acceleration) is the state of
    the middle render, i.e. mid-exposure, as the hand-eye loop's camera stamps its frames (before
    2026-12-04 it was the state at the exposure's end). Frame 0 is one render. The background is the scene rendered without the cube and the rod (post-
    processed with its own noise), as a calibration image of the empty scene would be.
    """
    xml, assets = scene_mjcf(scene, width, height)
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    d.qpos[0] = scene.release_rad
    steps = int(round(1.0 / (fps * m.opt.timestep)))
    m.opt.timestep = 1.0 / (fps * steps)
    dt = m.opt.timestep
    blur_steps = int(round(scene.exposure_s / dt)) if scene.exposure_s > 0 else 0
    k = camera_intrinsics(m, "eye", width, height)
    rng = np.random.default_rng(scene.seed + 7_000_003)
    frames = np.empty((n_frames, height, width, 3), np.uint8)
    track = np.empty((n_frames * steps + 2, 3))
    track_rot = np.empty((len(track), 3, 3))
    truth_at = np.zeros(n_frames, int)  # the step of each frame's true state (its middle render)
    shot_steps: list[int] = []
    renderer = mujoco.Renderer(m, height, width)
    offsets = set(np.linspace(0, blur_steps, exposure_samples).round().astype(int).tolist())
    shots: list[np.ndarray] = []
    try:
        mujoco.mj_forward(m, d)
        for s in range(len(track)):
            p, r = body_in_camera(m, d, "cube", "eye")
            track[s], track_rot[s] = p, r
            i = -(-(s - 1) // steps) if s >= 1 else 0  # the frame at or after this step
            back = 1 + i * steps - s  # steps before frame i's time
            if s >= 1 and i < n_frames and (back in offsets if blur_steps else back == 0):
                renderer.update_scene(d, camera="eye")
                shots.append(renderer.render().astype(np.float32))
                shot_steps.append(s)
                if back == 0:
                    img = np.mean(shots, axis=0)
                    # the middle render's (mid-exposure for an odd exposure_samples; the
                    # later of the two middle ones for an even count)
                    truth_at[i] = shot_steps[len(shot_steps) // 2]
                    shots, shot_steps = [], []
                    frames[i] = post_process(np.round(img).astype(np.uint8), scene, rng)
            mujoco.mj_step(m, d)
            mujoco.mj_forward(m, d)
        # the empty scene: the pendulum's geoms are in group 2, hidden here
        option = mujoco.MjvOption()
        option.geomgroup[2] = 0
        renderer.update_scene(d, camera="eye", scene_option=option)
        background = post_process(renderer.render(), scene, rng)
    finally:
        renderer.close()
    pos, vel, acc = sampled_motion(track, steps, n_frames, dt, truth_at)
    seq = RenderedSequence(frames, k, truth_at * dt, pos, track_rot[truth_at], vel, acc)
    return seq, background


def world_from_camera(scene: RandomScene, width: int = 640, height: int = 480):
    """(R_world_cam, p_world_cam) of the scene's camera (pinhole convention)."""
    xml, assets = scene_mjcf(scene, width, height)
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    mujoco.mj_camlight(m, d)  # the camera's pose (cam_xpos, cam_xmat): not set by mj_kinematics
    return camera_pose_world(m, d, "eye")
