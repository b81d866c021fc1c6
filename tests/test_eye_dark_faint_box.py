"""A box of the wall's hue whose faces are both faint and darker than the wall
(``detect.faint_foreground_regions(shadows=False)``, ``TrackConfig.faint_unshadowed``, issue 24)
against drawn images: the shadow test takes such a face for the wall in shadow, and its colour
difference is under the usual blob threshold.
"""

import dataclasses

import numpy as np
import pytest

from hec_jax.geometry import detect
from hec_jax.geometry.track import RANDOMIZED_BENCHMARK, BoxTracker

WALL_RGB = np.array([120.0, 60.0, 140.0])  # grey levels
DARKER = 0.9  # the face: the wall's colour x 0.9 in every channel (14 grey levels at most)
FACE = (slice(200, 260), slice(300, 360))  # rows, columns of the face
# the rendered frames' size (640 x 480), so the tracker's jitted functions are the other tests'
INTRINSICS = np.array([[300.0, 0.0, 320.0], [0.0, 300.0, 240.0], [0.0, 0.0, 1.0]])


def _frame(seed: int, face: bool = True) -> np.ndarray:
    """(480, 640, 3) uint8: the wall, with the face where ``face``, sensor noise of 2 grey
    levels (seeded)."""
    image = np.broadcast_to(WALL_RGB, (480, 640, 3)).copy()
    if face:
        image[FACE] *= DARKER
    image += np.random.default_rng(seed).normal(0.0, 2.0, image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _covers_face(box) -> bool:
    """The blob's box (x0, y0, x1, y1) overlaps the face's by IoU >= 0.7."""
    x0, y0, x1, y1 = box
    fx0, fx1, fy0, fy1 = FACE[1].start, FACE[1].stop, FACE[0].start, FACE[0].stop
    inter = max(0, min(x1, fx1) - max(x0, fx0)) * max(0, min(y1, fy1) - max(y0, fy0))
    union = (x1 - x0) * (y1 - y0) + (fx1 - fx0) * (fy1 - fy0) - inter
    return inter / union >= 0.7


@pytest.mark.parametrize("seed", range(3))
def test_only_the_faint_blobs_without_the_shadow_test_find_a_dark_face_of_the_wall_s_hue(seed):
    image, background = _frame(seed), _frame(100 + seed, face=False)
    kwargs = dict(min_threshold=3.0, core=0.4)
    assert not detect.foreground_regions(image, background, core=0.4)  # 14 < 20 grey levels
    assert not detect.foreground_regions(image, background, core=0.4, shadows=False)
    shadowed = detect.faint_foreground_regions(image, background, **kwargs)
    assert not any(_covers_face(box) for box, _ in shadowed)  # the wall in shadow, to the test
    found = detect.faint_foreground_regions(image, background, shadows=False, **kwargs)
    assert len(found) == 1 and _covers_face(found[0][0])
    # nothing where there is no face: the noise stays under the threshold
    empty = _frame(200 + seed, face=False)
    assert not detect.faint_foreground_regions(empty, background, shadows=False, **kwargs)


# slow (8-10 s on a worker, the tracker's traces): the default suite checks the option in the
# tracker on rendered frames (tests/test_eye_randomized.py, the faint candidates' test)
@pytest.mark.slow
@pytest.mark.parametrize("option", [False, True])
def test_the_search_tries_the_dark_face_s_blob_only_with_faint_unshadowed(option):
    """The search from scratch (the benchmark's preset, one thread) on the drawn frame: the
    window centres it searches from [px]. With the option one lies at the face's centre
    (329.5, 229.5); without it no blob is found, so nothing is searched."""
    config = dataclasses.replace(RANDOMIZED_BENCHMARK, threads=1, faint_unshadowed=option)
    tracker = BoxTracker(INTRINSICS, 0.1, 30.0, config, background=_frame(100, face=False))
    centres = []
    search = tracker._search

    def recording(centre, *args):
        centres.append(np.asarray(centre))
        return search(centre, *args)

    tracker._search = recording
    tracker.update(_frame(0))
    near = [np.linalg.norm(c - np.array([329.5, 229.5])) < 3.0 for c in centres]
    assert any(near) == option
    if not option:
        assert not centres
