"""A lower LSD threshold where the box differs little from its background (``detect.lsd_quant``,
``TrackConfig.lsd_contrast``, issue 24) against drawn images: a face a few grey levels off the
wall beside a bright floor in the same window, whose contrast stretch therefore does nothing.
"""

import dataclasses

import numpy as np
import pytest

from hec_jax.geometry import detect
from hec_jax.geometry.track import RANDOMIZED_BENCHMARK, BoxTracker, TrackConfig

WALL, FACE, FLOOR = 100.0, 92.0, 220.0  # grey levels
FACE_X0 = 40.0  # the face's left edge [px, intrinsics convention]: columns 40.. are the face


def _faint_face(seed: int) -> np.ndarray:
    """(120, 160) uint8: a wall, a face 8 grey levels darker (rows 30-89, columns 40-79), a
    bright floor below row 100, sensor noise of 2 grey levels."""
    gray = np.full((120, 160), WALL)
    gray[30:90, 40:80] = FACE
    gray[100:, :] = FLOOR
    gray += np.random.default_rng(seed).normal(0.0, 2.0, gray.shape)
    return np.clip(np.round(gray), 0, 255).astype(np.uint8)


def _on_left_edge(segments: np.ndarray) -> np.ndarray:
    """Segments within 1 px of the face's left edge along their whole length."""
    x, y = segments[:, :, 0], segments[:, :, 1]
    near = np.all(np.abs(x - FACE_X0) <= 1.0, axis=1) & np.all((y > 28) & (y < 92), axis=1)
    return near


def _edge_covered(segments: np.ndarray) -> float:
    """The length of the face's left edge (60 px) the segments on it cover [px]."""
    on_edge = segments[_on_left_edge(segments)]
    return float(np.sum(np.linalg.norm(on_edge[:, 1] - on_edge[:, 0], axis=-1)))


def test_lsd_quant_scales_with_the_contrast():
    assert detect.lsd_quant(40.0, 20.0) == detect.LSD_QUANT  # enough contrast: OpenCV's bound
    assert detect.lsd_quant(20.0, 20.0) == detect.LSD_QUANT
    assert detect.lsd_quant(10.0, 20.0) == pytest.approx(0.5 * detect.LSD_QUANT)
    assert detect.lsd_quant(1.0, 20.0) == detect.LSD_MIN_QUANT  # at least a quarter
    with pytest.raises(ValueError, match="quant"):
        detect.detect_segments(_faint_face(0), quant=0.0)


@pytest.mark.parametrize("seed", range(4))
def test_a_lower_threshold_finds_a_faint_edge_the_stretch_cannot(seed):
    gray = _faint_face(seed)
    roi = (0, 0, gray.shape[1], gray.shape[0])
    assert detect.stretch_gain(gray) == 1.0  # the floor spans the window's range
    default = detect.detect_segments(gray, roi, stretch=True)
    assert _edge_covered(default) == 0.0
    quant = detect.lsd_quant(abs(FACE - WALL), 40.0)  # a step of 8 grey levels of 40: 0.4
    assert quant == detect.LSD_MIN_QUANT
    faint = detect.detect_segments(gray, roi, stretch=True, quant=quant)
    assert _edge_covered(faint) >= 0.6 * 60.0  # most of the edge


@pytest.mark.parametrize("contrast", [0.0, -5.0])
def test_the_tracker_refuses_a_contrast_that_is_not_positive(contrast):
    intrinsics = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="lsd_contrast"):
        BoxTracker(intrinsics, 0.1, 30.0, TrackConfig(lsd_contrast=contrast))


@pytest.mark.parametrize("seed", range(2))
def test_the_tracker_finds_the_faint_face_s_edge_with_lsd_contrast(seed):
    """The tracker's window (``_moving_segments``, the benchmark's preset, one thread) on a drawn
    RGB frame: a bluish face (90, 90, 110) on a grey wall (100), a luminance step of 8 grey
    levels and a colour difference of 10, under a thin bright top face, above a bright floor.
    The median difference over the window's foreground mask is 12 grey levels: with
    ``lsd_contrast`` 20 the gray segments are found at LSD's bound 1.2 and cover the face's
    left edge; without it, none lies on that edge."""
    rng = np.random.default_rng(seed)
    background = np.full((120, 160, 3), WALL)
    background[100:] = FLOOR
    frame = background.copy()
    frame[30:90, 40:80] = (90.0, 90.0, 110.0)
    frame[27:30, 40:80] = 200.0

    def noisy(image):
        return np.clip(np.round(image + rng.normal(0.0, 2.0, image.shape)), 0, 255).astype(np.uint8)

    background, frame = noisy(background), noisy(frame)
    gray = detect.to_gray(frame)
    intrinsics = np.array([[500.0, 0.0, 80.0], [0.0, 500.0, 60.0], [0.0, 0.0, 1.0]])
    roi = (10, 10, 110, 110)
    covered = {}
    for contrast in (None, 20.0):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, lsd_contrast=contrast, threads=1)
        tracker = BoxTracker(intrinsics, 0.1, 30.0, cfg, background)
        tracker._frame_rgb = frame  # as update() sets it for the frame being processed
        window = tracker._foreground_window(*tracker._difference_pair(gray), roi)
        if contrast is not None:
            assert window[3] == 12.0
            assert detect.lsd_quant(window[3], contrast) == pytest.approx(1.2)
        else:
            assert window[3] is None
        covered[contrast] = _edge_covered(tracker._moving_segments(gray, roi))
    assert covered[None] == 0.0
    assert covered[20.0] >= 0.6 * 60.0
