"""MuJoCo/MJX model of the experimental set-up of Sec. 6.1 (Terauchi, Tanaka, Tsuji).

Modelling choices (see also ``scene.xml``):

* Arm: a 6-link serial chain whose motion is confined to the vertical x-z plane. The three pitch
  joints (shoulder, elbow, wrist; axes normal to the plane) are actuated by torque motors with
  limits 100 / 60 / 20 N m. The other three joints of the 6-DOF arm (base yaw, forearm roll, wrist
  roll) are *welded*: their links keep their masses, but carry no joint, i.e. they are held
  perfectly rigid at zero. This is the physically honest limit of the paper's "motions
  restricted to the vertical 2D plane" without very stiff servo loops that would need a smaller
  time step. A welded link's geom sits in the body of the link it is welded to (turret in base,
  forearm_b in forearm, flange in wrist), as MuJoCo's ``fusestatic`` would place it: the same
  masses, inertias and shapes (M, bias forces and sensors agree with a body-per-link model to
  1e-14 relative), with 9 bodies in a tree 5 deep instead of 12 and 8, which MJX's per-level
  body-tree passes pay for on every step (session 11: 1.38x MJX physics alone on an H100).
  Each active joint has armature 0.02 kg m^2 and viscous damping 0.2 N m s/rad; the controller
  accounts for both through M (qM includes armature) and h = qfrc_bias - qfrc_passive.
* Hand: a sphere (radius 0.04 m, 0.3 kg) whose centre is the end-effector point X_e, the hand body
  origin and its COM (so ``xfrc_applied`` on the hand acts at X_e). A 3-axis force sensor sits on
  the wrist side of the hand (site ``ft_sensor``).
* Object: a 0.1 m wooden cube (0.7 kg) on a 0.6 m steel rod (radius 3 mm) from a ceiling hinge at
  (0.35, 0, 1.25) m, swinging in the same plane.
* Contact: only the hand sphere and the cube, through an explicit frictionless pair (condim 1,
  solref 0.005), so that the contact force passes through the hand centre and Eq. 39 with a 2-D
  force is exact. Every other geom has contype = conaffinity = 0.
* Camera ``eye``: fixed, optical axis along world +y, fovy 45 deg, 640x480 intended, in front of
  a black void. ``lab.lab_model`` puts a room around the set-up and moves the camera to an oblique
  pose, for rendering only (issue 24, point 5).
* Time step 1 ms, semi-implicit Euler with joint damping integrated explicitly (eulerdamp off).
"""

# first: mujoco.mjx without its warp lines (see _quiet_import)
from hec_jax.mjx_scene import _quiet_import  # noqa: F401, I001


from hec_jax.mjx_scene.camera import (
    IMAGE_HEIGHT,
    IMAGE_WIDTH,
    camera_id,
    camera_intrinsics,
    camera_pose_world,
    project,
)
from hec_jax.mjx_scene.model import (
    ARM_JOINTS,
    CUBE_EDGE,
    HAND_RADIUS,
    SCENE_XML,
    TASK_AXES,
    X_HOME,
    PendulumConditions,
    PendulumConfig,
    SceneIds,
    apply_conditions,
    default_conditions,
    load_mj_model,
    load_mjx_model,
    mj_model_with_conditions,
    scene_ids,
    set_solver_options,
    solve_posture,
    validate_conditions,
)
from hec_jax.mjx_scene.lab import SCENES, lab_model, scene_model
from hec_jax.mjx_scene.render import (
    RenderedSequence,
    SceneCamera,
    render_model_like,
    render_rollout,
    render_swing,
    with_plane_grid,
)
from hec_jax.mjx_scene.sim import (
    CQuantities,
    SimStep,
    Trajectory,
    bias_force,
    c_quantities,
    dynamics_stages,
    full_mass_matrix,
    hand_contact_force,
    hand_contact_force_c,
    make_data,
    make_data_c,
    observe_stages,
    rollout,
    rollout_c,
    site_jacobians,
    site_position,
)

__all__ = [
    "ARM_JOINTS",
    "CUBE_EDGE",
    "HAND_RADIUS",
    "IMAGE_HEIGHT",
    "IMAGE_WIDTH",
    "SCENE_XML",
    "SCENES",
    "TASK_AXES",
    "CQuantities",
    "PendulumConditions",
    "PendulumConfig",
    "RenderedSequence",
    "SceneCamera",
    "SceneIds",
    "SimStep",
    "Trajectory",
    "apply_conditions",
    "c_quantities",
    "dynamics_stages",
    "camera_id",
    "camera_intrinsics",
    "camera_pose_world",
    "default_conditions",
    "hand_contact_force",
    "full_mass_matrix",
    "bias_force",
    "site_jacobians",
    "site_position",
    "hand_contact_force_c",
    "lab_model",
    "load_mj_model",
    "load_mjx_model",
    "make_data",
    "make_data_c",
    "observe_stages",
    "mj_model_with_conditions",
    "solve_posture",
    "X_HOME",
    "project",
    "render_model_like",
    "render_rollout",
    "render_swing",
    "rollout",
    "rollout_c",
    "scene_model",
    "scene_ids",
    "set_solver_options",
    "validate_conditions",
    "with_plane_grid",
]
