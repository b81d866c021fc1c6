"""The robot's self-mask in the camera loop, and its occlusion-aware variant (fast, no render)."""

from types import SimpleNamespace

import numpy as np

from hec_jax.geometry.box_model import project_corners_np
from hec_jax.geometry.track import BoxPrediction
from hec_jax.loop.camera_loop import (
    front_object_mask,
    mask_robot_and_replaced,
    robot_mask,
)

K = np.array([[200.0, 0.0, 80.0], [0.0, 200.0, 60.0], [0.0, 0.0, 1.0]])
SHAPE = (120, 160, 3)
EDGE = 0.1


def _camera(hand_world):
    """A camera at the world origin looking along +z (world = camera frame), a hand sphere."""
    model = SimpleNamespace(
        geom_type=np.array([2]),  # mjGEOM_SPHERE
        geom_size=np.array([[0.04, 0.0, 0.0]]),
    )
    data = SimpleNamespace(
        geom_xpos=np.array([hand_world], float), geom_xmat=np.eye(3).reshape(1, 9)
    )
    return SimpleNamespace(
        world_from_camera=(np.eye(3), np.zeros(3)), intrinsics=K, model=model, data=data
    )


def _prediction(centre, initialised=True):
    z = np.zeros(3)
    return BoxPrediction(
        np.bool_(initialised), np.asarray(centre, float), z, z, np.eye(3), np.eye(3)
    )


def test_front_object_mask_is_the_box_silhouette_only_when_the_box_is_in_front():
    box = (0.05, 0.0, 1.0)
    in_front = front_object_mask(SHAPE, _prediction(box), _camera((0.12, 0.0, 1.1)), [0], K, EDGE)
    corners = project_corners_np(np.eye(3), np.array(box), EDGE, K)
    lo, hi = corners.min(0), corners.max(0)
    assert in_front is not None and in_front.shape == SHAPE[:2]
    # the box's image: its centre pixel in, a pixel beyond its corners out
    centre = (K @ (np.array(box) / box[2]))[:2]
    assert in_front[int(centre[1]), int(centre[0])]
    assert not in_front[int(lo[1]) - 3, int(lo[0]) - 3] and not in_front[int(hi[1]) + 3, 5]
    area = in_front.sum()
    assert 0.8 * np.prod(hi - lo) < area <= np.prod(hi - lo + 2)
    # the hand nearer the camera, or no prediction: nothing is kept
    assert (
        front_object_mask(SHAPE, _prediction(box), _camera((0.12, 0.0, 0.9)), [0], K, EDGE) is None
    )
    assert (
        front_object_mask(SHAPE, _prediction(box, False), _camera((0, 0, 2.0)), [0], K, EDGE)
        is None
    )
    assert front_object_mask(SHAPE, None, _camera((0, 0, 2.0)), [0], K, EDGE) is None


def test_mask_robot_leaves_kept_pixels_as_rendered():
    frame = np.full(SHAPE, 200, np.uint8)
    camera = _camera((0.0, 0.0, 1.0))  # the hand sphere in the image centre
    masked, _ = mask_robot_and_replaced(frame, camera, [0], 0.005)
    assert masked[60, 80].max() == 0  # painted black (no inpainting asked)
    keep = np.zeros(SHAPE[:2], bool)
    keep[55:65, 75:85] = True
    kept, _ = mask_robot_and_replaced(frame, camera, [0], 0.005, keep=keep)
    np.testing.assert_array_equal(kept[keep], frame[keep])
    assert kept[60, 72].max() == 0  # the rest of the hand's disc (radius 10 px) is still masked


def _mask_robot_numpy(frame, camera, geoms, margin, inpaint_geoms=(), keep=None):
    """The mask written with NumPy's boolean indexing (``mask_robot_and_replaced``'s frame before its OpenCV
    rewrite): the reference its output must match to the bit.
    """
    import cv2

    from hec_jax.loop.camera_loop import robot_mask

    rest = [g for g in geoms if g not in set(inpaint_geoms)]
    out = frame.copy()
    arm = robot_mask(frame.shape, camera, rest, margin)
    if keep is not None:
        arm[keep] = 0
    out[arm > 0] = 0
    if len(inpaint_geoms):
        hand = robot_mask(frame.shape, camera, inpaint_geoms, margin)
        if keep is not None:
            hand[keep] = 0
        ys, xs = np.nonzero(hand)
        if len(ys):
            h, w = hand.shape
            y0, y1 = max(ys.min() - 8, 0), min(ys.max() + 9, h)
            x0, x1 = max(xs.min() - 8, 0), min(xs.max() + 9, w)
            out[y0:y1, x0:x1] = cv2.inpaint(
                out[y0:y1, x0:x1], hand[y0:y1, x0:x1], 3, cv2.INPAINT_TELEA
            )
    return out


def test_mask_robot_matches_the_numpy_reference_bit_for_bit():
    rng = np.random.default_rng(7)
    # two spheres: one painted black, one inpainted, one of them at the image's border
    model = SimpleNamespace(geom_type=np.array([2, 2]), geom_size=np.array([[0.04, 0, 0]] * 2))
    for hand_at in ((0.0, 0.0, 1.0), (-0.38, -0.28, 1.0), (5.0, 5.0, 1.0)):  # centre, corner, out
        data = SimpleNamespace(
            geom_xpos=np.array([(0.15, 0.05, 0.8), hand_at], float),
            geom_xmat=np.tile(np.eye(3).reshape(1, 9), (2, 1)),
        )
        camera = SimpleNamespace(
            world_from_camera=(np.eye(3), np.zeros(3)), intrinsics=K, model=model, data=data
        )
        frame = rng.integers(0, 256, SHAPE, dtype=np.uint8)
        keep = np.zeros(SHAPE[:2], bool)
        keep[50:70, 70:90] = True
        for kw in ({}, {"inpaint_geoms": [1]}, {"inpaint_geoms": [1], "keep": keep}):
            np.testing.assert_array_equal(
                mask_robot_and_replaced(frame, camera, [0, 1], 0.005, **kw)[0],
                _mask_robot_numpy(frame, camera, [0, 1], 0.005, **kw),
            )
            # the pixels replaced (painted or inpainted): both spheres' discs, less the kept ones
            out, replaced = mask_robot_and_replaced(frame, camera, [0, 1], 0.005, **kw)
            expected = robot_mask(SHAPE, camera, [0, 1], 0.005) > 0
            expected &= ~kw.get("keep", np.zeros(SHAPE[:2], bool))
            np.testing.assert_array_equal(replaced, expected)
            np.testing.assert_array_equal(out[~replaced], frame[~replaced])
