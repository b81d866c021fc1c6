"""Line segments and the box's image region from camera frames (OpenCV, at the NumPy boundary).

Pixel convention: OpenCV puts pixel centres at integer coordinates, the intrinsics of the eye put
the image on [0, W] x [0, H] (centre W/2, H/2, pixel centres at k + 1/2). Every coordinate leaving
this module is in the intrinsics' convention (OpenCV coordinates + 0.5).

Detectors (``benchmarks/eye_pipeline.py`` measures them against the projected true edges):

* ``lsd``: ``cv2.createLineSegmentDetector`` (LSD, sub-pixel by construction), the default;
* ``hough``: ``cv2.Canny`` + ``cv2.HoughLinesP`` (integer end points), for comparison.
"""

from __future__ import annotations

import math
import threading

import cv2
import numpy as np

PIXEL_OFFSET = 0.5  # OpenCV pixel centre (integer) -> intrinsics convention (k + 1/2)
EDGE_MIN_STEP = 6.0  # [grey levels / px] the weakest step edge_points keeps by default
# LSD's bound on the gradient's quantisation error [grey levels] (OpenCV's default); LSD keeps the
# pixels whose gradient exceeds quant / sin(22.5 deg), 5.2 grey levels per pixel at the default
LSD_QUANT = 2.0
LSD_MIN_QUANT = 0.5  # the lowest :func:`lsd_quant` gives (a quarter of the default's threshold)
_LSD = threading.local()  # detectors per thread (an OpenCV detector keeps per-call state)


def check_frames(frames) -> np.ndarray:
    """Validate a (T, H, W, 3) uint8 RGB sequence; raises ValueError with the reason."""
    if not isinstance(frames, np.ndarray):
        frames = np.asarray(frames)
    if frames.dtype != np.uint8:
        raise ValueError(f"frames must be uint8 RGB, got dtype {frames.dtype}")
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must have shape (T, H, W, 3), got {frames.shape}")
    if frames.shape[0] == 0 or frames.shape[1] < 8 or frames.shape[2] < 8:
        raise ValueError(f"frames must hold at least one image of 8x8 px, got {frames.shape}")
    return frames


def to_gray(frame: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W) uint8 luminance."""
    return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)


def _lsd(quant: float = LSD_QUANT):
    detectors = getattr(_LSD, "detectors", None)
    if detectors is None:
        detectors = _LSD.detectors = {}
    if quant not in detectors:  # OpenCV's defaults but the quantisation bound
        detectors[quant] = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, 0.8, 0.6, quant)
    return detectors[quant]


def lsd_quant(contrast: float, full_contrast: float) -> float:
    """LSD's quantisation bound for a box that differs from its background by ``contrast`` grey
    levels: :data:`LSD_QUANT` at ``full_contrast`` or more, in proportion below, at least
    :data:`LSD_MIN_QUANT` (LSD's gradient threshold scales with it).
    """
    return float(np.clip(LSD_QUANT * contrast / full_contrast, LSD_MIN_QUANT, LSD_QUANT))


def clip_roi(roi, width: int, height: int):
    """Integer (x0, y0, x1, y1) clipped to the image, or None if empty."""
    x0, y0, x1, y1 = (
        int(np.floor(roi[0])),
        int(np.floor(roi[1])),
        int(np.ceil(roi[2])),
        int(np.ceil(roi[3])),
    )
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    return x0, y0, x1, y1


STRETCH_RANGE = 128.0  # grey levels a faint window's 1-99 percentile range is stretched to
STRETCH_MAX_GAIN = 16.0  # the most a window is stretched by


def stretch_contrast(patch: np.ndarray) -> np.ndarray:
    """``patch`` (uint8 gray) with its 1-99 percentile range stretched linearly to
    :data:`STRETCH_RANGE` grey levels if it spans fewer (gain at most :data:`STRETCH_MAX_GAIN`),
    else unchanged. LSD's gradient threshold is absolute (about 5 grey levels per pixel), so the
    edges of a box close to its background's grey pass it only stretched (its noise is stretched
    too; LSD's a-contrario test keeps the segments that noise alone would not give).
    """
    lo, gain = _stretch(patch)
    if gain == 1.0:
        return patch
    out = np.clip((patch.astype(np.float32) - np.float32(lo)) * np.float32(gain), 0, 255)
    return out.astype(np.uint8)


def stretch_gain(patch: np.ndarray) -> float:
    """The gain :func:`stretch_contrast` applies to ``patch`` (1: none)."""
    return _stretch(patch)[1]


def _stretch(patch: np.ndarray) -> tuple[float, float]:
    """(1st percentile, gain) of :func:`stretch_contrast` (gain 1: unchanged)."""
    if patch.size == 0:
        return 0.0, 1.0
    lo, hi = _percentile_uint8(patch, 0.01), _percentile_uint8(patch, 0.99)
    if hi - lo >= STRETCH_RANGE:
        return float(lo), 1.0
    return float(lo), float(STRETCH_RANGE / max(hi - lo, STRETCH_RANGE / STRETCH_MAX_GAIN))


def detect_segments(
    gray: np.ndarray,
    roi=None,
    method: str = "lsd",
    min_length: float = 5.0,
    stretch: bool = False,
    quant: float = LSD_QUANT,
) -> np.ndarray:
    """Line segments (N, 2, 2) [px, intrinsics convention] in ``gray`` (optionally inside a ROI).

    ``roi`` = (x0, y0, x1, y1) in pixels; segments shorter than ``min_length`` [px] are dropped.
    ``stretch``: a window (``roi`` given) of low contrast is stretched first
    (:func:`stretch_contrast`). ``quant``: LSD's quantisation bound (:data:`LSD_QUANT`; lower
    finds weaker edges, :func:`lsd_quant`).
    """
    if not quant > 0:
        raise ValueError(f"quant must be > 0, got {quant!r}")
    h, w = gray.shape
    box = (0, 0, w, h) if roi is None else clip_roi(roi, w, h)
    if box is None:
        return np.zeros((0, 2, 2))
    x0, y0, x1, y1 = box
    patch = np.ascontiguousarray(gray[y0:y1, x0:x1])
    if stretch and roi is not None:
        patch = stretch_contrast(patch)
    if method == "lsd":
        lines = _lsd(quant).detect(patch)[0]
    elif method == "hough":
        edges = cv2.Canny(patch, 40, 120)
        lines = cv2.HoughLinesP(
            edges, 1, np.pi / 360, threshold=8, minLineLength=int(min_length), maxLineGap=2
        )
    else:
        raise ValueError(f"method must be 'lsd' or 'hough', got {method!r}")
    if lines is None:
        return np.zeros((0, 2, 2))
    seg = np.asarray(lines, dtype=np.float64).reshape(-1, 2, 2)
    seg += np.array([x0, y0]) + PIXEL_OFFSET
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=-1)
    return seg[length >= min_length]


def pad_segments(segments: np.ndarray, max_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep the ``max_segments`` longest segments, zero-pad: ((M, 2, 2), (M,) bool mask)."""
    out = np.zeros((max_segments, 2, 2))
    mask = np.zeros(max_segments, bool)
    if len(segments):
        length = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=-1)
        keep = np.argsort(-length)[:max_segments]
        out[: len(keep)] = segments[keep]
        mask[: len(keep)] = True
    return out, mask


def _side_pixels(segments: np.ndarray, fraction: float, offset_px: float, shape, origin):
    """The two pixels (row, column index arrays, each (2, N)) ``offset_px`` to either side of
    each segment (N, 2, 2) [px, intrinsics convention] at ``fraction`` of its length, in a
    window of ``shape`` (h, w) whose top-left pixel is ``origin`` (clamped to the window).
    """
    a, d = segments[:, 0], segments[:, 1] - segments[:, 0]
    length = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
    normal = np.stack([-d[:, 1], d[:, 0]], 1) / length[:, None]
    centre = a + fraction * d - PIXEL_OFFSET - np.asarray(origin, np.float64)
    rows, cols = [], []
    for sign in (1.0, -1.0):
        q = centre + sign * offset_px * normal
        cols.append(np.clip(np.round(q[:, 0]).astype(int), 0, shape[1] - 1))
        rows.append(np.clip(np.round(q[:, 1]).astype(int), 0, shape[0] - 1))
    return np.stack(rows), np.stack(cols)


def texture_segments(
    segments: np.ndarray,
    foreground: np.ndarray,
    origin=(0, 0),
    offset_px: float = 3.0,
    fractions=(0.25, 0.5, 0.75),
) -> np.ndarray:
    """(N,) bool: the segments (N, 2, 2) [px] with foreground on both sides, ``offset_px`` to
    either side at each of ``fractions`` of their length: lines inside a moving object (its
    texture, or a crease between two of its faces), not its outline against the background.

    ``foreground``: (h, w) bool, a window of the frame whose top-left pixel is ``origin`` =
    (x0, y0) (e.g. :func:`foreground_mask`'s); sides outside it are read at its border.
    """
    segments = np.asarray(segments, np.float64).reshape(-1, 2, 2)
    out = np.ones(len(segments), bool)
    for fraction in fractions:
        rows, cols = _side_pixels(segments, fraction, offset_px, foreground.shape, origin)
        out &= foreground[rows[0], cols[0]] & foreground[rows[1], cols[1]]
    return out


def texture_families(
    segments: np.ndarray,
    inside: np.ndarray,
    least_lines: int = 3,
    angle_deg: float = 5.0,
    separation_px: float = 1.5,
    steps: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) bool: the segments (N, 2, 2) [px] inside a box's image (``inside``, (N,) bool, e.g.
    :func:`texture_segments`) that lie in a family of at least ``least_lines`` distinct parallel
    lines inside it: a texture (wood grain), not the box's edges.

    A convex box shows at most one inner edge (both faces beside it visible) of each of its
    three edge directions; its other visible edges are on the outline, with background on one
    side. Parallel 3D edges project to nearly parallel image lines, so two or more distinct
    parallel lines inside the box's image are texture or creases but for one of them, and three
    or more cannot be the box's edges but for one. Segments within ``angle_deg`` [deg] of one
    another's direction are parallel; their lines are distinct where their mid points' offsets
    along the normal differ by more than ``separation_px`` [px] (collinear pieces of one line
    count once). Outline segments (``inside`` False) are never flagged. ``steps``: optional
    (N,) grey steps across the segments (:func:`segment_steps`); where given, the line of the
    family's segment with the largest step (the likeliest boundary of two faces) is kept.
    """
    segments = np.asarray(segments, np.float64).reshape(-1, 2, 2)
    inside = np.asarray(inside, bool)
    out = np.zeros(len(segments), bool)
    if inside.sum() < least_lines:
        return out
    index = np.flatnonzero(inside)
    d = segments[index, 1] - segments[index, 0]
    angle = np.arctan2(d[:, 1], d[:, 0]) % np.pi
    middle = segments[index].mean(1)
    # row i: the inside segments parallel to segment i, their mid points' offsets along its normal
    turn = (angle[None, :] - angle[:, None] + np.pi / 2) % np.pi - np.pi / 2  # in [-pi/2, pi/2)
    family = np.abs(turn) <= np.deg2rad(angle_deg)
    normal = np.stack([-np.sin(angle), np.cos(angle)], 1)
    offsets = np.sort(np.where(family, normal @ middle.T, np.inf), axis=1)  # the family first
    members = family.sum(1)
    gaps = np.diff(np.where(np.isfinite(offsets), offsets, 0.0), axis=1)
    between = np.arange(gaps.shape[1])[None, :] < (members - 1)[:, None]  # gaps in the family
    lines = 1 + np.count_nonzero(between & (gaps > separation_px), axis=1)
    flagged = lines >= least_lines
    if steps is not None:  # keep the line of the family's strongest step
        step = np.where(family, np.asarray(steps, np.float64)[index][None, :], -np.inf)
        strongest = np.argmax(step, axis=1)
        own = np.einsum("ij,ij->i", normal, middle)
        flagged &= (
            np.abs(own - (normal @ middle.T)[np.arange(len(index)), strongest]) > separation_px
        )
    out[index] = flagged
    return out


def segment_steps(
    segments: np.ndarray, gray: np.ndarray, offset_px: float = 2.0, samples: int = 8
) -> np.ndarray:
    """(N,) the grey step across each segment (N, 2, 2) [px]: the mean absolute difference of
    ``gray`` ((H, W), the whole frame) ``offset_px`` to either side, at ``samples`` points from
    0.15 to 0.85 of its length [grey levels].
    """
    segments = np.asarray(segments, np.float64).reshape(-1, 2, 2)
    total = np.zeros(len(segments))
    for fraction in np.linspace(0.15, 0.85, samples):
        rows, cols = _side_pixels(segments, fraction, offset_px, gray.shape, (0, 0))
        sides = gray[rows, cols].astype(np.float64)
        total += np.abs(sides[0] - sides[1])
    return total / samples


def background_model(frames: np.ndarray, samples: int = 25) -> np.ndarray:
    """Per-pixel median (H, W) uint8 gray of up to ``samples`` evenly spaced frames.

    Valid as a background only for a static camera and an object that moves; a static object is
    part of it (then :func:`foreground_region` finds nothing and the caller searches the full image).
    """
    idx = np.unique(np.linspace(0, len(frames) - 1, min(samples, len(frames))).astype(int))
    return np.median(np.stack([to_gray(frames[i]) for i in idx]), axis=0).astype(np.uint8)


class Background:
    """A background image ((H, W) gray or (H, W, 3) RGB uint8) with what :func:`difference`
    computes from it alone, computed once and kept: an RGB background's channels as float32
    floored at 1 (the shadow test's denominators) and its pixels whose channels are all at least
    24 grey levels. Every function here that takes a background takes one of these too, with
    the same results bit for bit (``tests/test_eye_tracker.py``); the tracker keeps one per
    given background (its search from scratch differences the whole frame twice a frame).

    ``background[y0:y1, x0:x1]`` is the window as a :class:`Background` (its terms are views of
    the kept ones); :meth:`blurred` the background box-filtered, kept per kernel.
    """

    def __init__(self, image: np.ndarray, terms=None):
        self.image = np.asarray(image)
        self._terms = terms  # (floors (3,), lit) of an RGB background, made on first use
        self._blurred: dict = {}

    shape = property(lambda self: self.image.shape)
    ndim = property(lambda self: self.image.ndim)
    dtype = property(lambda self: self.image.dtype)

    def terms(self) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """(float32 channels floored at 1, bool pixels with every channel >= 24) of an RGB
        background.
        """
        if self._terms is None:
            bgs = cv2.split(self.image)
            floors = tuple(cv2.max(b.astype(np.float32), 1.0) for b in bgs)
            self._terms = (floors, cv2.min(cv2.min(bgs[0], bgs[1]), bgs[2]) >= 24)
        return self._terms

    def __getitem__(self, window) -> Background:
        rows, cols = window
        terms = None
        if self.image.ndim == 3:
            floors, lit = self.terms()
            terms = (tuple(f[rows, cols] for f in floors), lit[rows, cols])
        return Background(self.image[rows, cols], terms)

    def blurred(self, ksize: tuple[int, int]) -> Background:
        """``cv2.blur(image, ksize)`` as a :class:`Background` (kept per ``ksize``)."""
        if ksize not in self._blurred:
            self._blurred[ksize] = Background(cv2.blur(self.image, ksize))
        return self._blurred[ksize]


def _background_image(background) -> np.ndarray:
    return background.image if isinstance(background, Background) else background


_SHADOW_RATIO = (0.25, 0.92)  # difference's default shadow_ratio


def difference(
    image: np.ndarray,
    background: np.ndarray | Background,
    shadow_ratio=_SHADOW_RATIO,
    shadow_tol: float = 0.08,
) -> np.ndarray:
    """(H, W) uint8 absolute difference of two gray images, or the largest over the channels of
    two RGB images (a box of another colour but the same luminance as the background shows).

    RGB only: a pixel that is the background darkened by the same factor in every channel (within
    ``shadow_tol``), the factor in ``shadow_ratio``, is a shadow (e.g. the box's own, on the floor
    or a wall: it moves with the box and has its outline) and gets difference 0. Background
    channels darker than 24 grey levels are not tested (their ratios are noise). None: no shadow
    test (a box of the background's hue, darker, passes it as a shadow).
    """
    kept = background if isinstance(background, Background) else None
    background = _background_image(background)
    diff = cv2.absdiff(image, background)
    if diff.ndim != 3:
        return diff
    # per channel with OpenCV (10x NumPy's time on a tracking window), the same float32
    # arithmetic: ratio = image / max(background, 1), its channel mean (c0 + c1) + c2 over 3,
    # the largest deviation from it (bit-identical to NumPy's: tests/test_eye_tracker.py)
    d0, d1, d2 = cv2.split(diff)
    out = cv2.max(cv2.max(d0, d1), d2)
    if shadow_ratio is None:
        return out
    floors, lit = (kept if kept is not None else Background(background)).terms()
    # pixel by pixel, so in blocks of rows that stay in the cache (a whole frame's float32
    # planes do not), each the same arithmetic
    rows = max(1, _SHADOW_BLOCK_PX // out.shape[1])
    for y in range(0, out.shape[0], rows):
        block = slice(y, y + rows)
        shadow = _shadow(image[block], [f[block] for f in floors], shadow_ratio, shadow_tol)
        out[block][shadow & lit[block]] = 0
    return out


_SHADOW_BLOCK_PX = 65536  # pixels per block of difference's shadow test


class FrameDifferences:
    """:func:`difference` of one frame to one background, window by window, each window kept.

    ``differences(box, shadow_ratio)``, ``box`` = (x0, y0, x1, y1) inside the image [px], is
    ``difference(image[y0:y1, x0:x1], background[y0:y1, x0:x1], shadow_ratio)`` (a new array),
    bit for bit: the difference is pixel by pixel, so a window inside one computed before (with
    the same ``shadow_ratio``) is copied from it, and another is computed and kept. A tracker's
    checks of one frame ask for windows inside the one its detection window asked for first.
    :meth:`faint` keeps the faint foreground's differences of blurred windows (one asked for
    again is copied).
    Calls from several threads are safe (a pixel computed twice is written the same value).
    """

    def __init__(self, image: np.ndarray, background: np.ndarray | Background):
        self.image = image
        self.background = background
        # the background's blurred copies kept (a gray array's too)
        kept = isinstance(background, Background)
        self._blurred_background = background if kept else Background(background)
        self._lock = threading.Lock()
        # key -> ((H, W) uint8 plane, [boxes (x0, y0, x1, y1) whose pixels in it are known])
        self._planes: dict = {}
        self._faint: dict = {}  # (box, blur_px, shadow_ratio) -> the faint window's difference

    def _check(self, box) -> None:
        h, w = self.image.shape[:2]
        x0, y0, x1, y1 = box
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise ValueError(f"window {tuple(box)} is not a non-empty box inside the {w}x{h} image")

    def __call__(self, box, shadow_ratio=_SHADOW_RATIO) -> np.ndarray:
        """(y1 - y0, x1 - x0) uint8: the difference of the window ``box`` (integers, inside the
        image), computed or copied from a kept window that holds it.

        Raises:
            ValueError: ``box`` is empty or not inside the image.
        """
        self._check(box)
        x0, y0, x1, y1 = box
        key = None if shadow_ratio is None else tuple(shadow_ratio)
        with self._lock:
            if key not in self._planes:
                self._planes[key] = (np.empty(self.image.shape[:2], np.uint8), [])
            plane, boxes = self._planes[key]
            known = any(
                b[0] <= x0 and b[1] <= y0 and x1 <= b[2] and y1 <= b[3] for b in tuple(boxes)
            )
        if known:
            return plane[y0:y1, x0:x1].copy()
        window = (slice(y0, y1), slice(x0, x1))
        diff = difference(self.image[window], self.background[window], shadow_ratio)
        plane[window] = diff
        with self._lock:
            boxes.append((x0, y0, x1, y1))  # after its pixels are written
        return diff

    def faint(self, box, blur_px: int = 5, shadow_ratio=_SHADOW_RATIO) -> np.ndarray:
        """(y1 - y0, x1 - x0) uint8: :func:`difference` of the window ``box`` (integers, inside
        the image) blurred by a ``blur_px`` square (``cv2.blur``, its border reflected at the
        window's sides) and the whole background blurred, cut to the window: the difference
        of :func:`faint_window` and :func:`faint_foreground_regions`, bit for bit.

        Only a window asked for before (the same box, blur and shadow test; a search from
        scratch asks for the whole frame's more than once) is copied from the kept one: the
        blur of a window inside another differs from it along its sides (and computing
        those sides apart costs more than a tracked box's window).

        Raises:
            ValueError: ``box`` is empty or not inside the image.
        """
        self._check(box)
        key = (tuple(box), blur_px, None if shadow_ratio is None else tuple(shadow_ratio))
        with self._lock:
            kept = self._faint.get(key)
        if kept is None:
            kept = self._faint_direct(box, blur_px, shadow_ratio)
            with self._lock:
                self._faint[key] = kept
        return kept.copy()

    def _faint_direct(self, box, blur_px: int, shadow_ratio) -> np.ndarray:
        """The faint difference of the window ``box``, computed (as :func:`faint_window`)."""
        x0, y0, x1, y1 = box
        k = (blur_px, blur_px)
        blurred = cv2.blur(np.ascontiguousarray(self.image[y0:y1, x0:x1]), k)
        return difference(blurred, self._blurred_background.blurred(k)[y0:y1, x0:x1], shadow_ratio)

    def of(self, image, background) -> bool:
        """Whether these are the frame and background this object differences."""
        return image is self.image and background is self.background


def _differences_of(image, background, differences) -> FrameDifferences:
    """``differences``, checked to be a :class:`FrameDifferences` of ``image`` and
    ``background``, or a new one where it is None.
    """
    if differences is None:
        return FrameDifferences(image, background)
    if not differences.of(image, background):
        raise ValueError("differences is not a FrameDifferences of this image and background")
    return differences


def _window_difference(image, background, box, shadow_ratio, differences) -> np.ndarray:
    """``difference`` of the window ``box`` = (x0, y0, x1, y1), from ``differences`` (a
    :class:`FrameDifferences` of ``image`` and ``background``) where given.
    """
    if differences is None:
        x0, y0, x1, y1 = box
        return difference(image[y0:y1, x0:x1], background[y0:y1, x0:x1], shadow_ratio)
    return _differences_of(image, background, differences)(box, shadow_ratio)


def _shadow(image: np.ndarray, floors: list, shadow_ratio, shadow_tol: float) -> np.ndarray:
    """(H, W) bool: :func:`difference`'s shadow test of an RGB ``image`` against the float32
    background channels floored at 1 (``floors``), the lit test left out.
    """
    # a window of a frame is split from a contiguous copy (OpenCV splits a strided one row by
    # row, 3x the time)
    channels = cv2.split(np.ascontiguousarray(image))
    ratio = [cv2.divide(c.astype(np.float32), f) for c, f in zip(channels, floors, strict=True)]
    mean = cv2.add(cv2.add(ratio[0], ratio[1]), ratio[2]) / np.float32(3.0)
    deviation = cv2.max(
        cv2.max(cv2.absdiff(ratio[0], mean), cv2.absdiff(ratio[1], mean)),
        cv2.absdiff(ratio[2], mean),
    )
    return (mean >= shadow_ratio[0]) & (mean <= shadow_ratio[1]) & (deviation <= shadow_tol)


def foreground_regions(
    gray: np.ndarray,
    background: np.ndarray,
    threshold: int = 20,
    open_px: int = 5,
    count: int = 3,
    core: float = 0.0,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> list[tuple[tuple[int, int, int, int], float]]:
    """Bounding boxes (x0, y0, x1, y1) and areas [px^2] of the ``count`` largest moving blobs.

    ``gray`` and ``background`` are both (H, W) gray or both (H, W, 3) RGB (:func:`difference`;
    ``shadows`` False: without its shadow test, so the pixels it takes for shadows count).
    Where the object was in the background image, the difference shows a blob too (a "ghost");
    the caller tries each blob. ``core`` > 0: each blob cut to its compact core
    (:func:`_compact_core`; a rod too thick for the opening is cut off the box).
    ``differences``: a :class:`FrameDifferences` of ``gray`` and ``background`` to take the
    difference from (and keep it in), or None.
    """
    box = (0, 0, gray.shape[1], gray.shape[0])
    diff = _window_difference(
        gray, background, box, _SHADOW_RATIO if shadows else None, differences
    )
    return _largest_blobs(diff > threshold, open_px, count, core)


def faint_foreground_regions(
    image: np.ndarray,
    background: np.ndarray,
    blur_px: int = 5,
    noise_factor: float = 4.0,
    min_threshold: float = 6.0,
    open_px: int = 5,
    count: int = 3,
    core: float = 0.0,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> list[tuple[tuple[int, int, int, int], float]]:
    """:func:`foreground_regions` for a box close to the background's colour: the difference
    (:func:`difference`, shadows included) of both images blurred by a ``blur_px`` square (the
    sensor noise averages out, a box's faces do not), thresholded at ``noise_factor`` x its
    median over the frame (most pixels are background: the median is the noise's level), at
    least ``min_threshold`` grey levels. ``shadows`` False: the same threshold on the difference
    without the shadow test (a box of the background's hue, darker, passes that test as a
    shadow). ``differences``: as :func:`faint_window`'s (the whole frame's kept).
    """
    differences = _differences_of(image, background, differences)
    frame = (0, 0, image.shape[1], image.shape[0])
    diff = differences.faint(frame, blur_px)
    threshold = max(min_threshold, noise_factor * _median_uint8(diff))
    if not shadows:
        diff = differences.faint(frame, blur_px, None)
    return _largest_blobs(diff > threshold, open_px, count, core)


def faint_threshold(
    image: np.ndarray,
    background: np.ndarray,
    blur_px: int = 5,
    noise_factor: float = 4.0,
    min_threshold: float = 6.0,
) -> float:
    """The threshold [grey levels] :func:`faint_foreground_regions` puts on the blurred
    difference of this frame: ``noise_factor`` x its median over the frame (the noise's level),
    at least ``min_threshold``. A property of the camera and the scene's light: a tracker can
    take it once (:func:`foreground_mask`'s ``faint_threshold``).
    """
    diff = FrameDifferences(image, background).faint(
        (0, 0, image.shape[1], image.shape[0]), blur_px
    )
    return max(min_threshold, noise_factor * _median_uint8(diff))


def _percentile_uint8(x: np.ndarray, q: float) -> float:
    """``float(np.percentile(x, 100 q))`` of a uint8 array, bit for bit (its default linear
    method: the order statistics around (n - 1) q, interpolated as NumPy's ``_lerp``), from
    the histogram instead of a partition of the pixels (``docs/eye_randomized.md``).
    """
    n = x.size
    below = np.cumsum(np.bincount(x.ravel(), minlength=256))
    index = (n - 1) * q
    lower = int(np.floor(index))
    gamma = index - lower
    a = int(np.searchsorted(below, lower, side="right"))  # sorted[lower]
    b = int(np.searchsorted(below, min(lower + 1, n - 1), side="right"))  # sorted[lower + 1]
    diff = float(b - a)
    return float(b) - diff * (1.0 - gamma) if gamma >= 0.5 else float(a) + diff * gamma


def _median_uint8(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a uint8 array from its histogram (a tenth of the time)."""
    n = x.size
    below = np.cumsum(np.bincount(x.ravel(), minlength=256))
    lower = int(np.searchsorted(below, (n - 1) // 2, side="right"))  # sorted[(n - 1) // 2]
    upper = int(np.searchsorted(below, n // 2, side="right"))  # sorted[n // 2]
    return float(lower) if lower == upper else 0.5 * (lower + upper)


def _largest_blobs(mask: np.ndarray, open_px: int, count: int, core: float = 0.0):
    """Bounding boxes and areas of the ``count`` largest connected blobs (>= 16 px) of a bool
    mask opened with an ``open_px`` square, largest first; with ``core`` > 0 each cut to its
    compact core first (:func:`_compact_core`).
    """
    mask = mask.astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((open_px, open_px), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA])
    out = []
    for b in order[:count]:
        x, y, w, h, area = stats[b]
        if area < 16:
            continue
        box = (int(x), int(y), int(x + w), int(y + h))
        if core > 0:
            got = _compact_core(labels[y : y + h, x : x + w] == b, core)
            if got is None:
                continue
            (cx0, cy0, cx1, cy1), area = got
            box = (box[0] + cx0, box[1] + cy0, box[0] + cx1, box[1] + cy1)
        out.append((box, float(area)))
    return sorted(out, key=lambda r: -r[1]) if core > 0 else out


def _compact_core(blob: np.ndarray, core: float):
    """Bounding box (in ``blob``'s window) and area of the largest piece of a bool blob that
    survives an opening by a disk of radius ``core`` x its largest inscribed radius (at least
    2 px): a box's square-ish silhouette keeps most of itself, a rod or string narrower than
    that radius is cut off. None if nothing survives.
    """
    padded = np.pad(blob.astype(np.uint8), 1)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1]
    radius = max(2.0, core * float(dist.max()))
    k = int(2 * np.ceil(radius) + 1)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    kept = cv2.dilate((dist >= radius).astype(np.uint8), disk) & blob.astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(kept, connectivity=8)
    if n <= 1:
        return None
    j = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h, area = stats[j]
    return (int(x), int(y), int(x + w), int(y + h)), float(area)


def foreground_region(
    gray: np.ndarray, background: np.ndarray, threshold: int = 20, open_px: int = 5
) -> tuple[tuple[int, int, int, int], float] | None:
    """Bounding box (x0, y0, x1, y1) and area [px^2] of the largest moving blob, or None.

    Difference to the background, thresholded, opened with an ``open_px`` square (removes thin
    things such as a rod or a string), largest connected component.
    """
    diff = cv2.absdiff(gray, background)
    mask = (diff > threshold).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((open_px, open_px), np.uint8))
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h, area = stats[best]
    if area < 16:
        return None
    return (int(x), int(y), int(x + w), int(y + h)), float(area)


def edge_points(
    gray: np.ndarray,
    edges_px: np.ndarray,
    usable: np.ndarray,
    spacing: float = 2.0,
    search: float = 2.5,
    step: float = 0.25,
    end_margin: float = 3.0,
    min_step: float = EDGE_MIN_STEP,
    blur: float = 0.8,
    interpolation: int = cv2.INTER_LINEAR,
    blurred: np.ndarray | None = None,
    short_end_margin: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel edge points along predicted model edges ("moving edges").

    For every usable edge (``edges_px`` (E, 2, 2) [px, intrinsics convention], ``usable`` (E,))
    points every ``spacing`` px (``end_margin`` px from the corners) search along the edge normal
    within +-``search`` px for the strongest intensity step of the smoothed image, located to
    sub-pixel precision by a parabola through the derivative peak. Steps weaker than ``min_step``
    [grey levels / px] are dropped; ``blur`` is the Gaussian's sigma [px]. Only the points
    within ``search`` + 2 px of the image are sampled (the same grid along each edge; an edge
    far outside, as a wrong fit can project, costs nothing). Returns (points (N, 2) [px], edge
    index (N,)). ``blurred``: :func:`edge_blur` of ``gray`` and ``blur``, if already made; None:
    only the window the samples read is smoothed (:func:`sample_window`), the same values as
    the whole image's :func:`edge_blur` there. ``short_end_margin``: an edge too short for
    ``end_margin`` (under 2 ``end_margin`` + ``spacing`` px, which gets no point) is sampled from
    this many px of its corners instead, where it is at least twice as long; longer edges as
    before. None: short edges get no point (as before).
    """
    if short_end_margin is not None and not short_end_margin > 0:
        raise ValueError(f"short_end_margin must be positive or None, got {short_end_margin}")
    offs = np.arange(-search, search + 1e-9, step)
    h, w = gray.shape[:2]
    pad = search + 2.0  # [px] points farther outside the image sample only its replicated border
    use = np.flatnonzero(usable)
    if not len(use):
        return np.zeros((0, 2)), np.zeros(0, int)
    starts = edges_px[use, 0]  # the usable edges' only (as the loop read them)
    deltas = edges_px[use, 1] - starts
    lengths = np.hypot(deltas[:, 0], deltas[:, 1])
    pts, kept, counts, units = [], [], [], []
    for j, e in enumerate(use):
        a, d = starts[j], deltas[j]
        length = float(lengths[j])
        margin = end_margin
        if not length >= 2 * end_margin + spacing:  # also NaN
            if short_end_margin is None or not length >= 2 * short_end_margin:
                continue
            margin = short_end_margin  # a short edge (short_end_margin)
        u = d / length
        # the points every ``spacing`` from ``margin``, those within ``pad`` of the image
        # only (a wrong fit's edge can project to millions of px)
        lo, hi = _inside_interval(a, u, length, (-pad, -pad, w + pad, h + pad))
        first = margin + spacing * max(np.ceil((lo - margin) / spacing), 0.0)
        ts = np.arange(first, min(hi, length - margin) + 1e-9, spacing)
        if ts.size == 0:
            continue
        pts.append(a + ts[:, None] * u)
        kept.append(e)
        counts.append(len(ts))
        units.append(u)
    if not pts:
        return np.zeros((0, 2)), np.zeros(0, int)
    pts = np.concatenate(pts)
    ids = np.repeat(np.asarray(kept), counts)
    units = np.stack(units)  # (K, 2) each kept edge's direction
    normals = np.stack([-units[:, 1], units[:, 0]], axis=1)[np.repeat(np.arange(len(kept)), counts)]
    samp = pts[:, None, :] + offs[None, :, None] * normals[:, None, :] - PIXEL_OFFSET
    map_x, map_y = samp[..., 0].astype(np.float32), samp[..., 1].astype(np.float32)
    if blurred is None:
        x0, y0, x1, y1 = sample_window(map_x, map_y, w, h, blur)
        img = edge_blur(gray[y0:y1, x0:x1], blur)
        # an integer taken from a float32 coordinate inside [0, 2^24) is exact: remap reads the
        # same pixel at the same sub-pixel fraction of the window
        map_x, map_y = map_x - np.float32(x0), map_y - np.float32(y0)
    else:
        img = blurred
    vals = cv2.remap(img, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)
    deriv = np.abs(vals[:, 2:] - vals[:, :-2]) / (2 * step)  # at offs[1:-1]
    i = np.argmax(deriv[:, 1:-1], axis=1) + 1
    rows = np.arange(len(i))
    y0, y1, y2 = deriv[rows, i - 1], deriv[rows, i], deriv[rows, i + 1]
    den = y0 - 2 * y1 + y2
    delta = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    offset = offs[1:-1][i] + np.clip(delta, -0.5, 0.5) * step
    keep = y1 >= min_step
    found = pts + offset[:, None] * normals
    return found[keep], ids[keep]


def edge_blur(gray: np.ndarray, blur: float = 0.8) -> np.ndarray:
    """The smoothed image :func:`edge_points` samples: ``gray`` as float32, Gaussian sigma
    ``blur`` [px].
    """
    return cv2.GaussianBlur(gray.astype(np.float32), (0, 0), blur)


# [px] the column multiple a smoothed window starts and ends at (or the image's edge). OpenCV's
# separable filter runs its SIMD lanes from the row's first pixel: a window aligned to the lanes
# computes each pixel with the same operations as the whole image (with another alignment, a
# pixel a lane computes in one and the scalar tail in the other can differ in the last bit).
# 64 covers 8 float32 lanes (AVX2, docs/realtime.md, "The tracker's host side") up to 16 lanes
# unrolled four times; tests/test_eye_tracker.py checks the equality on the machine it runs on.
SAMPLE_WINDOW_ALIGN = 64


def sample_window(map_x, map_y, width: int, height: int, blur: float) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) [px, OpenCV pixel indices, end exclusive] of ``gray`` whose
    :func:`edge_blur` (sigma ``blur`` [px]) holds, at every pixel a cubic or linear
    ``cv2.remap`` of the sample coordinates (``map_x``, ``map_y``) reads, the value of the whole
    image's: the samples' box grown by the Gaussian's radius (OpenCV's kernel for float32,
    ``round(8 sigma + 1) | 1`` taps), the interpolation's reach and a pixel of margin, clipped to
    the image, its columns aligned to :data:`SAMPLE_WINDOW_ALIGN`. Samples outside the image
    read its replicated edge either way (the window then reaches that edge).
    """
    taps = int(round(8.0 * blur + 1.0)) | 1
    grow = taps // 2 + 3  # the kernel's radius, cubic interpolation's reach (2 px) and a margin

    def span(coords, size: int) -> tuple[int, int]:  # the pixels read, within the image
        # (float32 coordinates: exact as Python floats, as is the clip's size - 1 < 2^24)
        lo = math.floor(min(max(float(np.min(coords)), 0.0), size - 1.0))
        hi = math.floor(min(max(float(np.max(coords)), 0.0), size - 1.0))
        return max(lo - grow, 0), min(hi + grow + 1, size)

    (x0, x1), (y0, y1) = span(map_x, width), span(map_y, height)
    a = SAMPLE_WINDOW_ALIGN
    return x0 // a * a, y0, min(-(-x1 // a) * a, width), y1


def _inside_interval(a, u, length: float, box) -> tuple[float, float]:
    """[px] the part (lo, hi) of the segment a + t u, t in [0, length], inside ``box`` =
    (x0, y0, x1, y1) (lo > hi: none).
    """
    lo, hi = 0.0, length
    for k, (low, high) in enumerate(((box[0], box[2]), (box[1], box[3]))):
        if abs(u[k]) < 1e-12:
            if not low <= a[k] <= high:
                return 1.0, 0.0
            continue
        t0, t1 = (low - a[k]) / u[k], (high - a[k]) / u[k]
        lo, hi = max(lo, min(t0, t1)), min(hi, max(t0, t1))
    return lo, hi


def foreground_mask(
    gray: np.ndarray,
    background: np.ndarray,
    roi,
    threshold: int = 12,
    dilate_px: int = 0,
    faint_threshold: float | None = None,
    faint_blur_px: int = 5,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> tuple[np.ndarray, tuple[int, int, int, int]] | None:
    """Pixels of ``gray`` (or RGB, :func:`difference`) that differ from the background inside ``roi`` = (x0, y0, x1, y1) [px]: ((h, w) bool
    mask of the clipped window, the window), or None if the window is empty.

    The absolute difference is smoothed by a 3x3 box filter (sensor noise) before the threshold
    [grey levels]; with ``faint_threshold`` [grey levels], the pixels where the difference of
    both images blurred by a ``faint_blur_px`` square (the window's, and the whole background's
    cut to the window) exceeds it are added (the faint foreground of
    :func:`faint_foreground_regions`: a box close to the background's colour). The mask is then
    dilated by ``dilate_px`` (a square of 2 dilate_px + 1). ``shadows`` False: both differences
    without :func:`difference`'s shadow test (the pixels it takes for shadows count).
    ``differences``: a :class:`FrameDifferences` of ``gray`` and ``background`` to take the
    window's difference from (the same numbers), or None.
    """
    h, w = gray.shape[:2]
    box = clip_roi(roi, w, h)
    if box is None:
        return None
    ratio = _SHADOW_RATIO if shadows else None
    diff = _window_difference(gray, background, box, ratio, differences)
    mask = cv2.blur(diff, (3, 3)) > threshold
    if faint_threshold is not None:
        mask |= faint_window(
            gray, background, box, faint_threshold, faint_blur_px, shadows, differences
        )
    mask = mask.astype(np.uint8)
    if dilate_px > 0:
        mask = cv2.dilate(mask, np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8))
    return mask.astype(bool), box


def _hull_mask(pts: np.ndarray, origin, shape) -> tuple[np.ndarray, np.ndarray]:
    """(hull, (h, w) bool mask of it) of the points (N, 2) [px, OpenCV convention] in a window
    whose top-left pixel is ``origin`` = (x0, y0).
    """
    hull = cv2.convexHull(np.round(pts - np.asarray(origin)).astype(np.int32))
    poly = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(poly, hull, 1)
    return hull, poly.astype(bool)


def _opened(mask: np.ndarray, open_px: int) -> np.ndarray:
    """``mask`` opened by an ``open_px`` square (thin things, such as a rod, dropped)."""
    if open_px <= 1:
        return mask
    kernel = np.ones((open_px, open_px), np.uint8)
    return cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)


def faint_window(
    image: np.ndarray,
    background,
    box,
    threshold: float,
    blur_px: int = 5,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> np.ndarray:
    """(h, w) bool: the window ``box`` = (x0, y0, x1, y1) (inside the image) of the faint
    foreground, the difference of the window blurred by a ``blur_px`` square and the whole
    background blurred (kept by a :class:`Background`) cut to the window, over ``threshold``
    (``shadows`` False: without :func:`difference`'s shadow test). ``differences``: a
    :class:`FrameDifferences` of ``image`` and ``background`` to take the difference from
    (:meth:`FrameDifferences.faint`, the same numbers), or None.
    """
    ratio = _SHADOW_RATIO if shadows else None
    return _differences_of(image, background, differences).faint(box, blur_px, ratio) > threshold


def foreground_fraction(
    gray: np.ndarray,
    background: np.ndarray,
    polygon_px: np.ndarray,
    threshold: int = 12,
    faint_threshold: float | None = None,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> float:
    """Fraction of the convex hull of ``polygon_px`` (N, 2) [px, intrinsics convention] whose
    pixels differ from the background (:func:`foreground_mask`, with its ``faint_threshold`` and
    ``shadows``); 0 if it lies outside the image.

    Confirms a model fit: a box fitted to the edges of a static object (clutter) lies on pixels
    that match the background. ``differences``: as :func:`foreground_mask`'s.
    """
    fractions = foreground_fractions(
        gray,
        background,
        np.asarray(polygon_px, np.float64)[None],
        threshold,
        faint_threshold,
        shadows,
        differences,
    )
    return float(fractions[0])


def _widened_roi(roi, width: int, height: int):
    """(x0, y0, x1, y1) of ``roi`` clipped to the image (None if that is empty), each side
    widened to at least :func:`clip_roi`'s 8 px around its centre and kept inside the image;
    None too for an image under 8 x 8 px, as :func:`clip_roi` gives.
    """
    x0, y0 = max(int(np.floor(roi[0])), 0), max(int(np.floor(roi[1])), 0)
    x1, y1 = min(int(np.ceil(roi[2])), width), min(int(np.ceil(roi[3])), height)
    if x1 <= x0 or y1 <= y0 or width < 8 or height < 8:
        return None

    def widen(lo, hi, size):
        if hi - lo >= 8:
            return lo, hi
        lo = min(max((lo + hi) // 2 - 4, 0), size - 8)
        return lo, lo + 8

    (x0, x1), (y0, y1) = widen(x0, x1, width), widen(y0, y1, height)
    return x0, y0, x1, y1


def foreground_fractions(
    gray: np.ndarray,
    background: np.ndarray,
    polygons_px: np.ndarray,
    threshold: int = 12,
    faint_threshold: float | None = None,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> np.ndarray:
    """(F,) the fraction of each polygon of ``polygons_px`` (F, N, 2) [px, intrinsics
    convention] whose pixels differ from the background, as :func:`foreground_fraction`
    measures one, but on one foreground mask over the window that holds them all (0 where that
    window is outside the image, or where a polygon is not finite). So a thin polygon (a box
    face seen nearly edge-on), whose own window would be under 8 px, is measured; and pixels
    near the border of a polygon's own window can read differently than in that window alone
    (the 3x3 blur's border). A window under :func:`clip_roi`'s 8 px (a box a few px across)
    is widened to 8 px inside the image (before session 75 it read 0). With one polygon:
    exactly :func:`foreground_fraction`.
    """
    pts = np.asarray(polygons_px, np.float64) - PIXEL_OFFSET
    out = np.zeros(len(pts))
    finite = np.all(np.isfinite(pts), axis=(1, 2))
    if not finite.any():
        return out
    lo, hi = np.floor(pts[finite].min((0, 1))), np.ceil(pts[finite].max((0, 1))) + 1
    roi = _widened_roi((lo[0], lo[1], hi[0], hi[1]), gray.shape[1], gray.shape[0])
    if roi is None:
        return out
    got = foreground_mask(
        gray,
        background,
        roi,
        threshold,
        faint_threshold=faint_threshold,
        shadows=shadows,
        differences=differences,
    )
    if got is None:
        return out
    mask, (x0, y0, _, _) = got
    for i in np.flatnonzero(finite):
        hull, inside = _hull_mask(pts[i], (x0, y0), mask.shape)
        # the part of the polygon outside the image counts as not confirmed
        full = max(float(cv2.contourArea(hull.astype(np.float32))), 1.0)
        covered = np.count_nonzero(mask & inside)  # (np.count_nonzero: a bool sum, faster)
        out[i] = float(covered) / max(float(np.count_nonzero(inside)), full)
    return out


# deep_shadow_share's factor range: below the shadow test's, down to a twentieth
DEEP_SHADOW_RATIO = (0.05, _SHADOW_RATIO[0])
# deep_shadow_share reads 0 where this share of the differing pixels is lighter than the
# background (a shadow has none but for noise)
LIGHTER_SHARE = 0.05
# deep_shadow_share's median filter [px] before the ratios (sensor noise; session 75)
DEEP_SHADOW_MEDIAN_PX = 5


def _median_filtered_pair(image, background, box, median_px: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.medianBlur`` by ``median_px`` (odd) of the RGB ``image`` and ``background`` (an
    array or a :class:`Background`), cut to ``box`` = (x0, y0, x1, y1): the same values as the
    whole frames filtered (each window padded by half the kernel; at the frame's own edges,
    its border replicated as ``medianBlur`` does).
    """
    x0, y0, x1, y1 = box
    height, width = image.shape[:2]
    half = median_px // 2
    px0, py0 = max(x0 - half, 0), max(y0 - half, 0)
    px1, py1 = min(x1 + half, width), min(y1 + half, height)

    def window(full):
        padded = cv2.copyMakeBorder(
            np.ascontiguousarray(full[py0:py1, px0:px1]),
            half - (y0 - py0),
            half - (py1 - y1),
            half - (x0 - px0),
            half - (px1 - x1),
            cv2.BORDER_REPLICATE,
        )
        return cv2.medianBlur(padded, median_px)[half : half + y1 - y0, half : half + x1 - x0]

    return window(image), window(np.asarray(_background_image(background)))


_CHANNEL_SUM = np.ones((1, 3), np.float32)  # cv2.transform's weights: the channels' sum


def deep_shadow_share(
    image: np.ndarray,
    background,
    polygon_px: np.ndarray,
    threshold: int = 12,
    ratio=DEEP_SHADOW_RATIO,
    rel_tol: float = 0.05,
    median_px: int = DEEP_SHADOW_MEDIAN_PX,
) -> float:
    """Of the pixels in the convex hull of ``polygon_px`` (N, 2) [px, intrinsics convention]
    where an RGB ``image`` differs from the background (an RGB array or a :class:`Background`)
    by more than ``threshold`` grey levels in some channel, the share that is a deep shadow:
    the background times one factor in ``ratio`` = [lo, hi) in every channel, the channels'
    ratios within ``rel_tol`` of that factor relative to it (a shadow darkens every channel
    alike), the background's channels all at least 24 grey levels (as :func:`difference`'s
    test). The hull's part outside the image is left out. 0 for a gray image or background
    (or one of another shape than the image's), a hull that is not finite or whose window is under
    :func:`clip_roi`'s 8 px, one with under 4 differing pixels, or one where at least
    ``LIGHTER_SHARE`` of the differing pixels are lighter than the background (on the mean of
    the channels): a shadow only darkens, so a lit face under the hull is not a shadow's.

    A fit to the cube's own shadow covers little but the shadow; a fit to the cube covers its
    faces, which differ from the background in hue, or are lit differently from one another.
    :func:`difference`'s shadow test stops at a factor of 0.25 with an absolute tolerance
    (0.08), which at lower factors would take many dark objects for shadows; the rendered
    scenes cast shadows down to about 0.1 (docs/eye_randomized.md, session 74). A relative
    tolerance still tells a shadow (the background's hue) from an object of another hue. A
    box of the background's hue with no face lighter than the background (a grey box on a
    lighter grey wall, lit from behind) reads as a shadow too: photometrically it is one.

    The tolerance is relative to the factor, so sensor noise counts for more the deeper the
    shadow: on the raw pixels a shadow at 0.23 reads 0.61 at 2 grey levels of noise and 0.33
    at 3 (session 74). So the ratios (not which pixels differ, nor the lighter ones) are
    taken on both images median-filtered by ``median_px`` (odd; 1: unfiltered): the filter
    removes most of the noise and, unlike a box filter, keeps a shadow's edges, so the hull's
    pixels next to the lit background stay the shadow's (docs/eye_randomized.md, session 75).
    """
    integral = isinstance(median_px, int | np.integer) and not isinstance(median_px, bool)
    if not integral or median_px < 1 or median_px % 2 == 0:
        raise ValueError(f"median_px must be an odd int >= 1, got {median_px!r}")
    image = np.asarray(image)
    background = np.asarray(_background_image(background))
    if image.ndim != 3 or background.shape != image.shape:
        return 0.0
    pts = np.asarray(polygon_px, np.float64) - PIXEL_OFFSET
    if not np.all(np.isfinite(pts)):
        return 0.0
    lo, hi = np.floor(pts.min(0)), np.ceil(pts.max(0)) + 1
    box = clip_roi((lo[0], lo[1], hi[0], hi[1]), image.shape[1], image.shape[0])
    if box is None:
        return 0.0
    x0, y0, x1, y1 = box
    _, inside = _hull_mask(pts, (x0, y0), (y1 - y0, x1 - x0))
    if image.dtype == np.uint8 and background.dtype == np.uint8 and image.shape[2] == 3:
        # the two early zeros' counts on the window with OpenCV: the same integers as below,
        # without gathering the hull's pixels as floats
        window_img, window_bg = image[y0:y1, x0:x1], background[y0:y1, x0:x1]
        channels = cv2.split(cv2.absdiff(window_img, window_bg))
        # compared as float32, as below (a float threshold is rounded to float32 there)
        largest = cv2.max(cv2.max(channels[0], channels[1]), channels[2]).astype(np.float32)
        differs = (largest > threshold) & inside
        n_differs = np.count_nonzero(differs)
        if n_differs < 4:
            return 0.0
        # the channels' signed difference summed (exact in int16): > 0 where the mean is
        signed = cv2.subtract(window_img, window_bg, dtype=cv2.CV_16S)
        lighter = differs & (cv2.transform(signed, _CHANNEL_SUM) > 0)
        if np.count_nonzero(lighter) >= LIGHTER_SHARE * n_differs:
            return 0.0
    img = image[y0:y1, x0:x1][inside].astype(np.float32)  # (P, 3)
    bg = background[y0:y1, x0:x1][inside].astype(np.float32)
    differs = np.abs(img - bg).max(-1) > threshold
    if differs.sum() < 4:
        return 0.0
    # a shadow only darkens: lighter pixels under the hull (a lit face) are no shadow's
    lighter = differs & ((img - bg).mean(-1) > 0)
    if lighter.sum() >= LIGHTER_SHARE * differs.sum():
        return 0.0
    if median_px > 1:
        # the ratios on both images median-filtered: sensor noise is filtered out, a shadow's
        # edges are kept
        img, bg = _median_filtered_pair(image, background, box, median_px)
        img, bg = img[inside].astype(np.float32), bg[inside].astype(np.float32)
    r = img / np.maximum(bg, np.float32(1.0))
    mean = r.mean(-1)
    dev = np.abs(r - mean[:, None]).max(-1)
    deep = (mean >= ratio[0]) & (mean < ratio[1]) & (dev <= rel_tol * mean)
    deep &= np.all(bg >= 24, axis=-1)
    return float(np.sum(deep & differs)) / float(differs.sum())


def outside_foreground_fraction(
    image: np.ndarray,
    background: np.ndarray,
    polygon_px: np.ndarray,
    threshold: int = 12,
    gap_px: float = 2.0,
    width: float = 0.15,
    open_px: int = 3,
    ignore: np.ndarray | None = None,
    differences: FrameDifferences | None = None,
) -> float:
    """Fraction of a ring just outside the convex hull of ``polygon_px`` (N, 2) [px, intrinsics
    convention] whose pixels differ from the background (:func:`foreground_mask`, opened by
    ``open_px`` to drop thin things such as a rod). The ring holds the pixels farther than
    ``gap_px`` from the hull (blur) and at most ``gap_px`` + ``width`` x the hull's size (the
    larger side of its bounding box, at least 2 px) from it; pixels outside the image, and
    where ``ignore`` ((H, W) bool, e.g. a known occluder) is True, are not counted. NaN where
    the ring has no pixel to count.

    Confirms a model fit: the background shows around a box's true silhouette, while a box
    fitted inside it (too far away, on the edges of its texture) has the box around it.
    ``differences``: as :func:`foreground_mask`'s.
    """
    pts = np.asarray(polygon_px, np.float64) - PIXEL_OFFSET
    if not np.all(np.isfinite(pts)):
        return float("nan")
    lo, hi = pts.min(0), pts.max(0)
    ring_px = max(2.0, width * float(np.max(hi - lo)))
    pad = gap_px + ring_px + 2
    window = (lo[0] - pad, lo[1] - pad, hi[0] + pad + 1, hi[1] + pad + 1)
    got = foreground_mask(image, background, window, threshold, differences=differences)
    if got is None:
        return float("nan")
    mask, (x0, y0, x1, y1) = got
    mask = _opened(mask, open_px)
    _, inside = _hull_mask(pts, (x0, y0), mask.shape)
    dist = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 3)
    ring = (dist > gap_px) & (dist <= gap_px + ring_px)
    if ignore is not None:
        ring &= ~np.asarray(ignore, bool)[y0:y1, x0:x1]
    count = np.count_nonzero(ring)
    return float(np.count_nonzero(mask & ring)) / count if count else float("nan")


def segments_in_mask(segments: np.ndarray, mask: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """The segments (N, 2, 2) [px, intrinsics convention] whose mid point and both end points lie
    in ``mask`` (a window whose top-left pixel is ``origin`` = (x0, y0)).
    """
    if not len(segments):
        return segments
    pts = np.concatenate([segments, segments.mean(1, keepdims=True)], axis=1)  # (N, 3, 2)
    # the pixel that holds the point: pixel j spans [j, j + 1) in the intrinsics convention
    ij = np.floor(pts - np.asarray(origin)).astype(int)
    h, w = mask.shape
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < w) & (ij[..., 1] >= 0) & (ij[..., 1] < h)
    ij = np.clip(ij, 0, [w - 1, h - 1])
    hit = mask[ij[..., 1], ij[..., 0]] & inside
    return segments[np.all(hit, axis=1)]


def foreground_iou(
    image: np.ndarray,
    background: np.ndarray,
    polygon_px: np.ndarray,
    threshold: int = 12,
    margin: float = 0.3,
    open_px: int = 3,
    faint_threshold: float | None = None,
    shadows: bool = True,
    differences: FrameDifferences | None = None,
) -> float:
    """Intersection over union of the convex hull of ``polygon_px`` (N, 2) [px, intrinsics
    convention] and the foreground (:func:`foreground_mask`, with its ``faint_threshold`` and
    ``shadows``, opened by ``open_px`` to drop thin things such as a rod) in a window of the
    hull's bounding box grown by ``margin`` of its size.

    Confirms a model fit found from scratch: a box fitted a few centimetres off, or to a static
    object, covers the moving blob poorly. 0 where the window leaves the image.
    ``differences``: as :func:`foreground_mask`'s.
    """
    pts = np.asarray(polygon_px, np.float64) - PIXEL_OFFSET
    if not np.all(np.isfinite(pts)):
        return 0.0
    lo, hi = pts.min(0), pts.max(0)
    pad = margin * float(np.max(hi - lo)) + 2
    roi = (lo[0] - pad, lo[1] - pad, hi[0] + pad, hi[1] + pad)
    got = foreground_mask(
        image,
        background,
        roi,
        threshold,
        faint_threshold=faint_threshold,
        shadows=shadows,
        differences=differences,
    )
    if got is None:
        return 0.0
    mask, (x0, y0, _, _) = got
    mask = _opened(mask, open_px)
    _, inside = _hull_mask(pts, (x0, y0), mask.shape)
    union = float(np.count_nonzero(mask | inside))
    return float(np.count_nonzero(mask & inside)) / union if union > 0 else 0.0
