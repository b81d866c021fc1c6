"""The eye: motion of a rigid object from images of 3D-parallel line segments (Secs. 2-3)."""

from hec_jax.geometry.camera import (
    check_intrinsics,
    intrinsics_from_fovy,
    normalized_to_pixel,
    pinhole_rotation_from_mujoco,
    pixel_to_normalized,
    project_points,
    project_to_pixels,
)
from hec_jax.geometry.paper_eye import PaperEye, PaperEyeConfig, PaperStep
from hec_jax.geometry.parallel_motion import (
    MotionEstimate,
    estimate_motion,
    estimate_motion_core,
)
from hec_jax.geometry.refine import TwoFrameMotion, two_frame_motion
from hec_jax.geometry.synthetic import SceneConfig, make_cube_scenes, rotation_error_deg
from hec_jax.geometry.track import (
    BoxPrediction,
    BoxTrack,
    BoxTracker,
    TrackConfig,
    TrackStep,
    track_box,
)

__all__ = [
    "BoxPrediction",
    "BoxTrack",
    "BoxTracker",
    "TrackStep",
    "TrackConfig",
    "TwoFrameMotion",
    "track_box",
    "two_frame_motion",
    "MotionEstimate",
    "PaperEye",
    "PaperEyeConfig",
    "PaperStep",
    "SceneConfig",
    "check_intrinsics",
    "estimate_motion",
    "estimate_motion_core",
    "intrinsics_from_fovy",
    "make_cube_scenes",
    "normalized_to_pixel",
    "pinhole_rotation_from_mujoco",
    "pixel_to_normalized",
    "project_points",
    "project_to_pixels",
    "rotation_error_deg",
]
