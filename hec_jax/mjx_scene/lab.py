"""A lab-like scene around the set-up, for rendering only (issue 24, point 5; NumPy/MuJoCo C).

:func:`lab_model` returns scene.xml with a room added (floor tiles, back and side walls, a
workbench and a shelf with boxes on them, the frame the pendulum hangs from), lights that cast
shadows, and the camera ``eye`` moved to an oblique pose from which the cube shows three faces.
Everything added is **visual only**:

* every added geom has contype = conaffinity = 0 (scene.xml's default) and sits in one static
  body ``lab`` appended after all of scene.xml's bodies, so the bodies, geoms, sites, joints and
  actuators of scene.xml keep their ids and come first (``render_model_like`` copies the
  simulated model's kinematic geometry onto that prefix);
* the MJX model the loop simulates is never built from it (``load_mj_model`` is unchanged);
  stepping this C model gives scene.xml's trajectory bit for bit (``tests/test_mjx_scene_lab.py``).

The camera's intrinsics and pose are read from this model by
:class:`~hec_jax.mjx_scene.render.SceneCamera`, as for the void scene: the eye is calibrated on
the model it sees.

World frame as scene.xml: z up, the swing plane is x-z (normal +y), the camera on the -y side.
"""

from __future__ import annotations

from typing import Literal

import mujoco
import numpy as np

from hec_jax.mjx_scene.model import SCENE_XML, load_mj_model

Scene = Literal["void", "lab"]
SCENES = ("void", "lab")

# Camera "eye" of the lab: aimed at a point between the catching hinge's (x = 0.55 m) and
# scene.xml's (x = 0.35 m) swing, at the height of the cube's path; elevation above the
# horizontal and azimuth from the swing plane's normal (-y), toward -x so the camera looks at the
# cube's -x face (the face turned away from the hand: the cube is in front of the hand, not the
# hand in front of the cube).
LAB_AIM = (0.42, 0.0, 0.62)  # [m] world point on the optical axis
LAB_ELEVATION_DEG = 30.0  # [deg] (issue 24: 25-35)
LAB_AZIMUTH_DEG = -32.0  # [deg] (issue 24: 25-40 off the normal)
# [m] camera to LAB_AIM: the swing (x 0.0-0.75 m) spans about half the image's width
LAB_DISTANCE_M = 1.75
LAB_FOVY_DEG = 45.0  # [deg] as scene.xml's camera


def orbit_position(target, elevation_deg: float, azimuth_deg: float, distance_m: float):
    """(3,) world position [m] of a camera ``distance_m`` from ``target`` (3,) [m], at
    ``elevation_deg`` above the horizontal and ``azimuth_deg`` from the swing plane's normal
    (-y; positive toward +x) [deg] (also the randomized benchmark's viewpoints).
    """
    el, az = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    d = np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), np.sin(el)])
    return target + distance_m * d


def look_at_xyaxes(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """MuJoCo camera ``xyaxes`` (6,) looking from ``pos`` at ``target`` [m], image x horizontal."""
    fwd = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return np.concatenate([right, up])


def lab_camera_position() -> np.ndarray:
    """(3,) world position of the lab's camera [m]."""
    return orbit_position(np.asarray(LAB_AIM), LAB_ELEVATION_DEG, LAB_AZIMUTH_DEG, LAB_DISTANCE_M)


def _box(body, name: str, centre, half, rgba, material: str = "") -> None:
    g = body.add_geom(
        name=name,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=list(map(float, centre)),
        size=list(map(float, half)),
        rgba=list(map(float, rgba)),
        contype=0,
        conaffinity=0,
    )
    if material:
        g.material = material


def _room(spec: mujoco.MjSpec) -> None:
    """The room's geoms and lights in a new static body ``lab`` (all straight-edged boxes)."""
    tex = spec.add_texture(
        name="lab_tiles",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        width=256,
        height=256,
        rgb1=[0.46, 0.47, 0.48],
        rgb2=[0.40, 0.41, 0.42],
    )
    mat = spec.add_material(name="lab_tiles", texrepeat=[12.0, 6.0])
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex.name
    lab = spec.worldbody.add_body(name="lab")
    # floor: 0.6 m tiles over 14 x 7 m (a plane just below scene.xml's, which is hidden)
    floor = lab.add_geom(
        name="lab_floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[1.5, 0.7, -0.001],
        size=[7.2, 3.6, 0.05],
        contype=0,
        conaffinity=0,
    )
    floor.material = "lab_tiles"
    wall = (0.80, 0.78, 0.72, 1)
    _box(lab, "lab_wall_back", (1.5, 2.2, 1.5), (7.2, 0.05, 1.5), wall)
    _box(lab, "lab_wall_left", (-1.9, 0.5, 1.5), (0.05, 3.6, 1.5), (0.72, 0.74, 0.76, 1))
    _box(lab, "lab_skirting", (1.5, 2.14, 0.05), (7.2, 0.01, 0.05), (0.25, 0.25, 0.27, 1))
    # workbench behind the swing: top 1.6 x 0.7 m at 0.75 m, four legs
    bench = (0.45, 1.25)
    _box(lab, "lab_bench_top", (*bench, 0.74), (0.8, 0.35, 0.02), (0.55, 0.42, 0.30, 1))
    for i, (dx, dy) in enumerate(((-0.76, -0.31), (0.76, -0.31), (-0.76, 0.31), (0.76, 0.31))):
        _box(
            lab,
            f"lab_bench_leg{i}",
            (bench[0] + dx, bench[1] + dy, 0.36),
            (0.025, 0.025, 0.36),
            (0.2, 0.22, 0.25, 1),
        )
    _box(lab, "lab_bench_box0", (0.0, 1.35, 0.84), (0.15, 0.1, 0.08), (0.2, 0.35, 0.6, 1))
    _box(lab, "lab_bench_box1", (0.95, 1.2, 0.81), (0.12, 0.12, 0.05), (0.6, 0.6, 0.58, 1))
    # shelf against the back wall, right of the bench: two uprights, three boards, boxes
    for i, x in enumerate((1.55, 2.45)):
        _box(lab, f"lab_shelf_side{i}", (x, 1.95, 0.9), (0.02, 0.2, 0.9), (0.3, 0.3, 0.32, 1))
    for i, z in enumerate((0.4, 1.0, 1.6)):
        _box(lab, f"lab_shelf_board{i}", (2.0, 1.95, z), (0.45, 0.2, 0.015), (0.62, 0.6, 0.55, 1))
    _box(lab, "lab_shelf_box0", (1.8, 1.95, 0.5), (0.15, 0.15, 0.085), (0.7, 0.55, 0.3, 1))
    _box(lab, "lab_shelf_box1", (2.2, 1.95, 1.12), (0.12, 0.12, 0.105), (0.35, 0.5, 0.35, 1))
    # the frame the pendulum hangs from: a beam along x just above the hinge block, two posts
    steel = (0.35, 0.36, 0.4, 1)
    _box(lab, "lab_beam", (0.5, 0.0, 1.30), (0.9, 0.03, 0.03), steel)
    for i, x in enumerate((-0.4, 1.4)):
        _box(lab, f"lab_post{i}", (x, 0.0, 0.65), (0.03, 0.03, 0.65), steel)
    # lights: a ceiling spot in front-left of the swing that casts the shadows (of the cube, rod,
    # arm and frame on the floor, bench and wall), and a fill light from the right without shadows
    lab.add_light(
        name="lab_key",
        pos=[-0.6, -1.2, 2.6],
        dir=list(map(float, np.array([1.0, 1.2, -2.0]) / np.linalg.norm([1.0, 1.2, -2.0]))),
        diffuse=[0.75, 0.75, 0.72],
        specular=[0.15, 0.15, 0.15],
        castshadow=True,
        cutoff=55.0,
        exponent=2.0,
    )
    lab.add_light(
        name="lab_fill",
        pos=[2.0, -1.5, 2.0],
        dir=list(map(float, np.array([-1.0, 1.0, -1.0]) / np.sqrt(3.0))),
        diffuse=[0.3, 0.3, 0.32],
        specular=[0.0, 0.0, 0.0],
        castshadow=False,
        cutoff=80.0,
    )


def lab_model(path=SCENE_XML) -> mujoco.MjModel:
    """scene.xml (``path``) with the lab around it and the oblique camera ``eye`` (module doc)."""
    spec = mujoco.MjSpec.from_file(str(path))
    cam = spec.camera("eye")
    pos = lab_camera_position()
    cam.pos = list(map(float, pos))
    cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    cam.alt.xyaxes = list(map(float, look_at_xyaxes(pos, np.asarray(LAB_AIM))))
    cam.fovy = LAB_FOVY_DEG
    # scene.xml's light stays, without a shadow map of its own (each shadow-casting light costs a
    # depth pass: only the lab's key light casts them); its bright floor is hidden under the lab's
    # tiles (rgba only: geom_size and the plane's contact settings are scene.xml's)
    for light in spec.lights:  # scene.xml's (the lab's are added below)
        light.castshadow = False
    spec.geom("floor").rgba = [0.0, 0.0, 0.0, 0.0]
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.15, 0.15, 0.15]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    spec.visual.quality.shadowsize = 1024
    spec.visual.map.znear = 0.05
    _room(spec)
    return spec.compile()


def scene_model(scene: Scene) -> mujoco.MjModel:
    """The C model the loop's camera renders: scene.xml itself (``"void"``) or :func:`lab_model`."""
    if scene == "void":
        return load_mj_model()
    if scene == "lab":
        return lab_model()
    raise ValueError(f"scene must be one of {', '.join(SCENES)}, got {scene!r}")
