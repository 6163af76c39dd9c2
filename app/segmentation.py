"""Background/foreground segmentation of one camera (thesis §2.2.3).

The thesis uses Stauffer-Grimson's adaptive mixture of Gaussians per pixel with
shadow suppression (Landabaso et al.). OpenCV's MOG2 is that model (Zivkovic's
improved Stauffer-Grimson) with a chromaticity/brightness shadow test: pixels it
labels as shadow (value 127) are background here. A small morphological opening
and closing removes speckle and fills pinholes.

Beyond the thesis, each selectable (``SegmentationParams``; 0 = off, the thesis's
MOG2 alone), measured against the simulator's true silhouettes with
``smartroom bench segmentation`` (docs/benchmarks.md, "Segmentation"; what was
tried: docs/history/segmentation.md):

- ``shadow_floor``: dark shadows. MOG2 keeps as foreground the contact shadows at the
  feet, darker than its ``tau`` (0.5); pixels of the floor (:func:`floor_region`)
  whose colour is the background's darkened down to ``shadow_floor`` within
  ``shadow_residual`` grey levels are shadow too, except within 2 pixels of what
  stays foreground (the feet and legs standing in that shadow).
- ``fill_holes``: holes enclosed by a silhouette up to an area (stripes of clothing
  close to the room's colour) are filled.
- ``second_chance``: a pixel next to the foreground that differs from the background
  by more than ``second_chance`` grey levels (below MOG2's own threshold, about 15.5
  with its initial variance) is foreground too (hysteresis at the outline).
- ``exposure``: light flicker and auto exposure. Each frame is scaled by the ratio of
  its brightness against the background (:func:`exposure_gain`) to that ratio's mean
  over about ``exposure`` frames, before MOG2 sees it.

Speed: the mask is computed at ``1/scale`` of the camera resolution, a resolution
matched to the projected footprint of the reconstruction's voxels
(:func:`matched_scale`: half size for 2 cm voxels, quarter size for 4 cm, in the
simulated room), which costs a quarter or a sixteenth of the full-size model.

Learning rate: MOG2 takes a new colour into the background once its weight passes
``1 - background ratio`` (0.1), i.e. after about ``0.1 / rate`` frames. OpenCV's
automatic rate (1/history, 1/500) lets a person who stands still for 2 s fade into
the background; the default 1e-4 takes 40 s, and still follows slow light changes.
A model that starts without an empty-room image learns at MOG2's fast start-up rate
for ``bootstrap`` frames first.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import cv2
import numpy as np
from numba import njit

__all__ = ["SegmentationParams", "CameraSegmenter", "camera_segmenter", "exposure_gain", "floor_region", "fill_holes",
           "estimate_background", "estimate_background_robust", "recording_background", "working_size", "matched_scale", "shrink",
           "YuvBackground"]


@dataclass
class SegmentationParams:
    scale: int = 2                  # the mask is 1/scale of the image size
    history: int = 500              # frames of MOG2 memory (its automatic rate is 1/history)
    var_threshold: float = 16.0     # squared Mahalanobis distance for foreground
    shadows: bool = True            # detect shadows (and treat them as background)
    shadow_threshold: float = 0.5   # MOG2 tau: a shadow is at most this much darker
    learning_rate: float = 1e-4     # per frame; -1: MOG2's automatic 1/history
    bootstrap: int = 100            # frames at the automatic rate when there is no background image
    open_px: int = 0                # opening kernel (removes speckle, and thin limbs); 0 = none
    close_px: int = 5               # closing kernel (fills holes); 0 = none
    shadow_floor: float = 0.15      # also shadow: down to this brightness ratio, background colour scaled; 0 = off
    shadow_residual: float = 6.0    # ... when the colour is within this many grey levels of the scaled background
    fill_holes: int = 400           # fill holes in the foreground up to this area (full-size pixels); 0 = none
    second_chance: float = 0.0      # a pixel next to the foreground that differs from the background by more
                                    # than this (grey levels, Euclidean over BGR) is foreground too; 0 = off
    exposure: int = 0               # frames: each frame's brightness is scaled to its running mean over about
                                    # this many first (flicker: :func:`exposure_gain`); 0 = off (the thesis
                                    # and the default: on the tuning seeds 50 lowers the mean MMTA, and its
                                    # tracking gain is one seed's; docs/benchmarks.md, "Flicker ...")

    @classmethod
    def from_params(cls, params: dict) -> "SegmentationParams":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in params.items() if k in names})


def working_size(width: int, height: int, scale: int) -> tuple[int, int]:
    """Size (w, h) of an image downscaled by an integer factor."""
    scale = max(1, int(scale))
    return width // scale, height // scale


def shrink(image: np.ndarray, scale: int) -> np.ndarray:
    """An image downscaled by an integer factor (pixel averaging). Powers of two go by
    repeated halving, several times faster than one ``INTER_AREA`` resize."""
    scale = max(1, int(scale))
    h, w = image.shape[:2]
    tw, th = working_size(w, h, scale)
    while scale > 1 and scale % 2 == 0:
        h, w = image.shape[:2]
        image = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        scale //= 2
    if image.shape[1] != tw or image.shape[0] != th:
        image = cv2.resize(image, (tw, th), interpolation=cv2.INTER_AREA)
    return image


#: the factor by which the reconstruction reduces the masks it sends with the voxels (its
#: ``silhouettes`` parameter's default; the pose stage's silhouette term)
SILHOUETTE_FACTOR = 2


def reduce_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    """A boolean mask reduced by an integer ``factor`` (a pixel is foreground when at least
    half of what it covers is); as is for a factor of 1."""
    mask = np.asarray(mask, bool)
    if int(factor) <= 1:
        return mask
    return shrink(mask.astype(np.float32), int(factor)) >= 0.5


def estimate_background(images) -> np.ndarray:
    """Empty-room image estimated as the per-pixel temporal median of frames spread
    over a recording (people move, so each pixel is background most of the time)."""
    stack = np.stack(list(images))
    return np.median(stack, axis=0).astype(np.uint8)


@njit(cache=True, nogil=True)
def _median_u8(vals, k):
    """The median of ``vals[:k]`` (uint8; the rounded mean of the middle two for an even count)."""
    v = np.sort(vals[:k])
    return v[k // 2] if k % 2 else (np.int32(v[k // 2 - 1]) + np.int32(v[k // 2]) + 1) // 2


@njit(cache=True, nogil=True)
def _masked_median(stack, masked, previous, min_count, out, uncertain):
    """Per pixel and channel, the median of the frames where the pixel is not masked;
    where fewer than ``min_count`` frames are left, the previous estimate (uncertain)."""
    n, h, w, ch = stack.shape
    vals = np.empty(n, dtype=np.uint8)
    for y in range(h):
        for x in range(w):
            m = 0
            for t in range(n):
                if not masked[t, y, x]:
                    m += 1
            if m < min_count:
                uncertain[y, x] = True
                for c in range(ch):
                    out[y, x, c] = previous[y, x, c]
                continue
            uncertain[y, x] = False
            for c in range(ch):
                k = 0
                for t in range(n):
                    if not masked[t, y, x]:
                        vals[k] = stack[t, y, x, c]
                        k += 1
                out[y, x, c] = _median_u8(vals, k)


@njit(cache=True, nogil=True)
def _agrees(stack, t, y, x, ref, threshold):
    """Whether frame ``t`` of ``stack`` at pixel (y, x) is within ``threshold`` of ``ref`` in every channel."""
    for c in range(stack.shape[3]):
        if abs(np.int32(stack[t, y, x, c]) - np.int32(ref[c])) > threshold:
            return False
    return True


@njit(cache=True, nogil=True)
def _agreeing(stack, y, x, ref, threshold):
    """How many frames of ``stack`` at pixel (y, x) are within ``threshold`` of ``ref`` (every channel)."""
    k = 0
    for t in range(stack.shape[0]):
        k += _agrees(stack, t, y, x, ref, threshold)
    return k


@njit(cache=True, nogil=True)
def _largest_agreeing(stack, threshold, min_count, out, uncertain):
    """Per pixel where no majority of the frames agrees with the estimate ``out``: the
    largest group of frames that agree with one of them (every channel within
    ``threshold``), when it is larger than the group that agrees with the estimate and
    holds ``min_count`` frames at least; its per-channel median replaces the estimate
    (and the pixel is no longer ``uncertain``)."""
    n, h, w, ch = stack.shape
    vals = np.empty(n, dtype=np.uint8)
    group = np.empty(n, dtype=np.int64)
    for y in range(h):
        for x in range(w):
            have = _agreeing(stack, y, x, out[y, x], threshold)
            if 2 * have > n:
                continue
            best, best_t = have, -1
            for t in range(n):
                k = _agreeing(stack, y, x, stack[t, y, x], threshold)
                if k > best:
                    best, best_t = k, t
            if best_t < 0 or best < min_count:
                continue
            uncertain[y, x] = False
            ref = stack[best_t, y, x].copy()
            m = 0
            for t in range(n):
                if _agrees(stack, t, y, x, ref, threshold):
                    group[m] = t
                    m += 1
            for c in range(ch):
                for i in range(m):
                    vals[i] = stack[group[i], y, x, c]
                out[y, x, c] = _median_u8(vals, m)


def estimate_background_robust(images, iterations: int = 2, threshold: int = 24, grow_px: int = 9,
                               min_share: float = 0.15, passers_by: bool = True) -> tuple[np.ndarray, float]:
    """Empty-room image of a recording with people in it: ``(background, uncertain)``.

    Starts from the per-pixel temporal median of the frames (BGR, spread over the
    recording) and then, ``iterations`` times, marks in every frame the pixels that
    differ from the current estimate by more than ``threshold`` grey levels in some
    channel (people, their shadows), grown by ``grow_px`` so their blurred outlines
    go too, and takes the median of what is left per pixel. A person who stood still
    for a while drags the plain median towards their colours (a ghost: holes in them,
    false foreground where they stood); once they have moved, the frames that show
    them differ from the room and are left out. Where fewer than ``min_share`` of the
    frames are left (someone there almost all the time) the pixel keeps the earlier
    estimate and counts as uncertain; ``uncertain`` is that share of the image.

    With ``passers_by`` (the default; False: the estimate as it was before 2026-12-02), a
    last pass mends the pixels where people passed in most of the frames, each in other
    clothes: the median is then a mixture that no frame shows (a smeared ghost, false
    foreground in every frame), and the masking above cannot leave those frames out,
    since all of them differ from it. Where no majority of the frames agrees with the
    estimate, the largest group of frames that agree with one another (every channel
    within ``threshold``) takes its place, when that group is larger than the one that
    agrees with the estimate and holds ``min_share`` of the frames: the room, seen
    between the passers-by (:func:`_largest_agreeing`). A person who stood still in most
    frames is a majority and stays in the estimate, as before (the other cameras' views
    paint them out, :mod:`app.background_views`).
    """
    stack = np.ascontiguousarray(np.stack(list(images)))
    n = len(stack)
    background = np.median(stack, axis=0).astype(np.uint8)
    uncertain = np.zeros(stack.shape[1:3], dtype=np.bool_)
    if n < 3:
        return background, 1.0
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (grow_px, grow_px)) if grow_px > 1 else None
    min_count = max(2, int(np.ceil(min_share * n)))
    for _ in range(iterations):
        masked = np.empty(stack.shape[:3], dtype=np.bool_)
        for t in range(n):
            diff = cv2.absdiff(stack[t], background).max(axis=2) > threshold
            d8 = diff.view(np.uint8)
            masked[t] = (cv2.dilate(d8, kernel) if kernel is not None else d8).view(bool)
        out = np.empty_like(background)
        _masked_median(stack, masked, background, min_count, out, uncertain)
        background = out
    if passers_by:
        _largest_agreeing(stack, threshold, min_count, background, uncertain)
    return background, float(uncertain.mean())


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
_KEEP = cv2.getStructuringElement(cv2.MORPH_RECT, (5, 5))
_NOWHERE = np.zeros((1, 1), dtype=np.uint8)


@njit(cache=True, nogil=True)
def _shadow_and_weak(image, reference, raw, region, floor, residual2, weak2, fg, weak):
    """Per pixel of MOG2's labels ``raw`` (255 foreground, 127 shadow, 0 background):
    ``fg`` = foreground that is not a shadow, ``weak`` = not a shadow and farther than
    ``sqrt(weak2)`` grey levels from the background ``reference`` (BGR, Euclidean).

    The shadow test is the brightness / colour distortion test MOG2 uses (after
    Horprasert et al. 1999; the thesis' §2.2.3 removes shadows with Landabaso et al.'s
    variant): brightness ratio ``a = <x, b> / <b, b>`` and colour distortion
    ``|x - a b|``, here with the distortion bounded in absolute grey levels
    (``sqrt(residual2)``: sensor noise is additive) instead of MOG2's bound scaled by
    ``a^2``, which gives up on shadows darker than MOG2's ``tau`` (contact shadows at
    the feet). It applies to the pixels MOG2 calls foreground where ``region`` is set
    (the floor), with ``floor <= a < 1``."""
    h, w = raw.shape
    for y in range(h):
        for x in range(w):
            r = raw[y, x]
            if r == 0 and weak2 <= 0:   # most of the image: background, nothing to test
                fg[y, x] = 0
                weak[y, x] = 0
                continue
            b0 = np.float32(reference[y, x, 0])
            b1 = np.float32(reference[y, x, 1])
            b2 = np.float32(reference[y, x, 2])
            x0 = np.float32(image[y, x, 0])
            x1 = np.float32(image[y, x, 1])
            x2 = np.float32(image[y, x, 2])
            shadow = r == 127
            if r == 255 and floor > 0 and region[min(y, region.shape[0] - 1), min(x, region.shape[1] - 1)]:
                bb = b0 * b0 + b1 * b1 + b2 * b2
                if bb > 400.0:
                    a = (x0 * b0 + x1 * b1 + x2 * b2) / bb
                    if floor <= a < 1.0:
                        d0, d1, d2 = x0 - a * b0, x1 - a * b1, x2 - a * b2
                        shadow = d0 * d0 + d1 * d1 + d2 * d2 <= residual2
            fg[y, x] = 1 if (r == 255 and not shadow) else 0
            if shadow or weak2 <= 0:
                weak[y, x] = 0
            else:
                d0, d1, d2 = x0 - b0, x1 - b1, x2 - b2
                weak[y, x] = 1 if d0 * d0 + d1 * d1 + d2 * d2 > weak2 else 0


def fill_holes(mask: np.ndarray, max_area: float) -> np.ndarray:
    """Fill, in place, the holes of a uint8 0/1 ``mask`` (background regions enclosed by
    foreground, 4-connected) of at most ``max_area`` pixels: stripes of clothing close
    to the room's colour, not the gap between an arm and the body (larger). The holes
    are the inner contours of the foreground (``cv2.findContours``, two levels); a
    hole's area is that of the polygon through the foreground pixels around it (a
    w x h hole: (w + 1)(h + 1)). 0.2 ms at 320x240, a tenth of labelling the background."""
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return mask
    holes = [c for c, h in zip(contours, hierarchy[0]) if h[3] >= 0 and cv2.contourArea(c) <= max_area]
    if holes:
        cv2.drawContours(mask, holes, -1, 1, thickness=cv2.FILLED)
    return mask


class CameraSegmenter:
    """Mixture-of-Gaussians background model of one camera."""

    def __init__(self, params: SegmentationParams, background: np.ndarray | None = None,
                 shadow_region: np.ndarray | None = None):
        self.params = params
        # where the dark-shadow test applies (bool at the mask size, e.g. :func:`floor_region`); None: nowhere
        self.shadow_region = None if shadow_region is None else np.ascontiguousarray(shadow_region, dtype=np.uint8)
        self.model = cv2.createBackgroundSubtractorMOG2(
            history=params.history, varThreshold=params.var_threshold, detectShadows=params.shadows)
        if params.shadows:
            self.model.setShadowThreshold(params.shadow_threshold)
        self._open = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.open_px,) * 2) if params.open_px else None
        self._close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.close_px,) * 2) if params.close_px else None
        self.trained = False
        self.frames = 0   # frames the model learnt from (the background images aside)
        self.small: np.ndarray | None = None   # the last frame at the mask's size
        self.reference: np.ndarray | None = None   # MOG2's background image (shadow test, second chance, exposure)
        self.gain = 1.0   # the last frame's brightness against the background's (``exposure``)
        self.usual_gain: float | None = None   # its running mean over about ``exposure`` frames
        if background is not None:
            self.learn_background([background])

    def learn_background(self, images) -> None:
        """Train the model on empty-room images (running mean over them)."""
        for i, img in enumerate(images):
            self.model.apply(shrink(img, self.params.scale), learningRate=1.0 / (i + 1))
        self.trained = True

    def _match_exposure(self, learn: bool = True) -> None:
        """Scale ``small`` by its gain against ``reference`` over that gain's running mean
        (``exposure``: the flicker goes, a steady offset stays; :func:`exposure_gain`)."""
        self.gain = exposure_gain(self.small, self.reference)
        if learn or self.usual_gain is None:
            self.usual_gain = self.gain if self.usual_gain is None else \
                self.usual_gain + (self.gain - self.usual_gain) / self.params.exposure
        flicker = self.gain / self.usual_gain
        if abs(flicker - 1.0) > 0.002:
            self.small = cv2.convertScaleAbs(self.small, alpha=1.0 / flicker)

    def apply(self, image: np.ndarray, prescaled: int = 1, learn: bool = True) -> np.ndarray:
        """Foreground mask (H/scale, W/scale) bool of one frame; the model keeps adapting
        (``learn`` False: it stays as it is, for a frame it has taken already).
        ``prescaled``: the image is already 1/prescaled of the camera's size (it divides scale)."""
        p = self.params
        self.frames += learn
        fast = learn and not self.trained and self.frames <= p.bootstrap
        # MOG2's automatic rate, 1 / min(2 n, history), over the frames it learnt from only
        # (its own n counts every call, a frame taken without learning too; fast: no
        # background image was learnt, so n is ``frames``)
        rate = 1.0 / min(2 * self.frames, p.history) if fast else p.learning_rate if learn else 0.0
        self.small = shrink(image, p.scale // prescaled)
        if p.exposure > 0 and not fast:
            if self.reference is None:
                self.reference = self.model.getBackgroundImage()   # None until the model has seen a frame
            if self.reference is not None:
                self._match_exposure(learn)
        raw = self.model.apply(self.small, learningRate=rate)
        if p.shadow_floor > 0 or p.second_chance > 0 or p.exposure > 0:
            if self.reference is None or (learn and (self.frames % 10 == 0 or fast)):
                self.reference = self.model.getBackgroundImage()
        if p.shadow_floor > 0 or p.second_chance > 0:
            fg = np.empty(raw.shape, dtype=np.uint8)
            weak = np.empty(raw.shape, dtype=np.uint8)
            region = self.shadow_region if self.shadow_region is not None else _NOWHERE
            _shadow_and_weak(self.small, self.reference, raw, region, np.float32(p.shadow_floor),
                             np.float32(p.shadow_residual ** 2), np.float32(p.second_chance ** 2), fg, weak)
            if p.shadow_floor > 0:   # feet stand in their own contact shadow: keep the outline of what stays
                fg |= cv2.dilate(fg, _KEEP) & (raw == 255)
            if p.second_chance > 0:
                fg |= cv2.dilate(fg, _CROSS) & weak
        else:
            fg = (raw == 255).astype(np.uint8)
        if self._open is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._open)
        if self._close is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, self._close)
        if p.fill_holes > 0:
            fill_holes(fg, max(1, p.fill_holes // (p.scale * p.scale)))
        return fg.view(bool)


def exposure_gain(image: np.ndarray, background: np.ndarray, step: int = 4) -> float:
    """The brightness of ``image`` against ``background`` (same size, BGR uint8): the
    median, over every ``step``-th pixel in both directions, of the ratio of their
    channel sums where the background is neither dark nor saturated, refined by the mean
    of the ratios within 3 % of it; 1.0 where too few probes count. People cover less
    than half of the probes in any camera but a blocked one, so the median is the
    room's.

    Used by :class:`CameraSegmenter` with ``exposure`` (beyond the thesis; issue 22):
    mains flicker and a camera's auto exposure scale the whole frame. The random
    scenes' flicker reaches 6 %, 10-15 grey levels on a bright floor, about MOG2's
    threshold (some 15.5 over the three channels at its initial variance), and a frame
    brighter than the model is no shadow: without an empty-room image (the background
    the median of flickering frames) the floor came and went as foreground (tuning seed
    55: false foreground 2.1 times the people's pixels). Each frame is scaled by its gain
    over the gain's running mean: the flicker goes and a steady offset stays. Scaling by
    the gain itself made the masks worse on the scenes with an empty-room image, whose
    frames are 2-3 % darker than that image throughout (the codec, the people's
    shadows), an offset that is no scale factor on every pixel."""
    f = image[::step, ::step].astype(np.float32).sum(axis=2).ravel()
    b = background[::step, ::step].astype(np.float32).sum(axis=2).ravel()
    ok = (b > 90.0) & (b < 720.0) & (f < 750.0)
    if ok.sum() < 64:
        return 1.0
    ratio = f[ok] / b[ok]
    med = float(np.median(ratio))
    near = ratio[np.abs(ratio - med) <= 0.03 * med]
    return float(near.mean()) if len(near) >= 32 else med


def floor_region(camera, room_min, room_max, scale: int = 1, step: float = 0.01) -> np.ndarray:
    """The pixels (bool, at ``1/scale`` of the camera's size) where the room's floor
    (z = 0 inside the room's bounds) is in view, furniture ignored: where a person's
    cast shadow can fall (the dark-shadow test of :class:`CameraSegmenter`)."""
    w, h = working_size(camera.width, camera.height, scale)
    xs = np.arange(room_min[0], room_max[0] + step / 2, step)
    ys = np.arange(room_min[1], room_max[1] + step / 2, step)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    uv = camera.project(pts) / scale
    ok = (np.abs(uv) < 1e6).all(axis=1)   # finite and near the image (far off it, a wide lens's distortion explodes)
    u, v = np.floor(uv[ok, 0]).astype(np.int64), np.floor(uv[ok, 1]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros((h, w), dtype=np.uint8)
    out[v[inside], u[inside]] = 1
    out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3)))
    return out.view(bool)


def recording_backgrounds(recording, frames: int = 25, still_people: bool = True, log=None, status=None,
                          passers_by: bool = True) -> dict:
    """Every camera's background of a recording (camera -> BGR image), as the
    segmentation worker makes them: the ``background/`` image where there is one, else the
    estimate from ``frames`` frames with the people left out
    (:func:`estimate_background_robust`, with or without ``passers_by``); with ``still_people``, the people who stood
    still through most of the recording, and so are in those estimates, are found with
    the other cameras' views of the room and painted out of them
    (:mod:`app.background_views`). ``log``: a logger told what was estimated and found;
    ``status``: called with a line before each long step (a worker's set-up status)."""
    from app.background_views import repaint_backgrounds

    out, estimated = {}, set()
    for cam in recording.cameras:
        background = recording.background(cam)
        if background is None:
            if status is not None:
                status(f"estimating the background of {cam} from {frames} frames of the recording")
            background, uncertain = estimate_background_robust(recording.sample(cam, frames), passers_by=passers_by)
            estimated.add(cam)
            if log is not None:
                log.warning("camera %s: no background image; estimated from %d frames of the recording with the "
                            "people left out; %.1f%% of the image stayed uncertain (someone there in almost every "
                            "frame)", cam, frames, 100 * uncertain)
        out[cam] = background
    if still_people and estimated and recording.calibration is not None:
        if status is not None:
            status("looking for people standing still in the estimated backgrounds")
        out, people, painted = repaint_backgrounds(recording.calibration, out, estimated)
        if log is not None and people:
            log.warning("%d people standing still were in the estimated backgrounds (at %s); painted out with the "
                        "other cameras' view of the room: %s pixels", len(people),
                        ", ".join(f"({p.centre[0]:.2f}, {p.centre[1]:.2f}) up to {p.top:.2f} m" for p in people),
                        ", ".join(f"{c} {n}" for c, n in painted.items()))
    return out


_BACKGROUNDS: dict = {}


def recording_background(recording, camera: str, frames: int = 25) -> np.ndarray:
    """A recording's background image of ``camera`` as the segmentation worker makes it
    (:func:`recording_backgrounds`; offline tools that must segment as the pipeline
    does). The recording's backgrounds are computed once per process."""
    key = (str(recording.path), int(frames))
    if key not in _BACKGROUNDS:
        _BACKGROUNDS.clear()
        _BACKGROUNDS[key] = recording_backgrounds(recording, frames)
    return _BACKGROUNDS[key][camera]


def camera_segmenter(params: SegmentationParams, background: np.ndarray | None, calibration=None,
                     camera: str | None = None) -> "CameraSegmenter":
    """A camera's segmenter; with the dark-shadow test on (``shadow_floor`` > 0) and a
    calibration, the test is limited to the pixels that see the floor."""
    region = None
    if params.shadow_floor > 0 and calibration is not None and camera is not None:
        region = floor_region(calibration.camera(camera), calibration.room_min, calibration.room_max, params.scale)
    return CameraSegmenter(params, background, shadow_region=region)


def warm_up(params: SegmentationParams, camera) -> None:
    """One throw-away frame through a model like a camera's (MOG2, the shadow kernel, the
    morphology), so the first real frame does not pay for loading the kernels."""
    image = np.zeros((camera.height, camera.width, 3), dtype=np.uint8)
    seg = CameraSegmenter(params, image)
    seg.apply(image + 40)


def matched_scale(calibration, voxel_size: float, pixels: float = 1.25) -> int:
    """The mask downscale (a power of two) at which a voxel still spans about
    ``pixels`` pixels, seen from the median camera-to-room-centre distance."""
    centre = (np.asarray(calibration.room_min) + np.asarray(calibration.room_max)) / 2
    cams = calibration.cameras
    dist = float(np.median([np.linalg.norm(c.centre - centre) for c in cams]))
    focal = float(np.median([c.K[0, 0] for c in cams]))
    footprint = focal * voxel_size / max(dist, 1e-6)
    scale = 1
    while footprint / (2 * scale) >= pixels and scale < 8:
        scale *= 2
    return scale


@njit(cache=True, nogil=True)
def _mahalanobis(yuv, mean, inv, shadow, out):
    """Squared Mahalanobis distance per pixel to the background mean or to its shadowed
    twin (Y scaled by ``1 - shadow``), whichever the pixel's luminance is nearer to."""
    h, w = out.shape
    for y in range(h):
        for x in range(w):
            my = mean[y, x, 0]
            dy = yuv[y, x, 0] - my
            if yuv[y, x, 0] < my * (1.0 - 0.5 * shadow):
                dy = yuv[y, x, 0] - my * (1.0 - shadow)
            du = yuv[y, x, 1] - mean[y, x, 1]
            dv = yuv[y, x, 2] - mean[y, x, 2]
            out[y, x] = (inv[0, 0] * dy * dy + inv[1, 1] * du * du + inv[2, 2] * dv * dv
                         + 2.0 * (inv[0, 1] * dy * du + inv[0, 2] * dy * dv + inv[1, 2] * du * dv))


class YuvBackground:
    """The background model of Caillette et al.'s fused reconstruction (CVIU 2007,
    §6.1): a Gaussian in YUV per pixel with a shadowed twin whose mean is 10 % darker
    in Y, chosen per pixel by a test on the luminance; :meth:`distance` gives the
    squared Mahalanobis distance ``d_M`` of every pixel of a frame (chi-square with 3
    degrees of freedom under the background hypothesis), which
    :mod:`app.reconstruction.fused` sums over a voxel's projected area.

    The paper learns a full covariance per pixel from empty-room frames. A recording
    holds one empty-room image, so here the mean is per pixel (that image, at the mask
    size) and the covariance is one per camera, estimated robustly from the residuals
    of the first frames (:meth:`fit_noise`: from the median absolute deviation, then
    without the pixels beyond the 99 % chi-square quantile, people and their shadows),
    with a floor of ``min_sigma`` grey levels per channel (compression and flicker).
    """

    def __init__(self, background: np.ndarray, shadow: float = 0.1, min_sigma: float = 2.0):
        self.mean = cv2.cvtColor(background, cv2.COLOR_BGR2YUV).astype(np.float32)
        self.shadow = float(shadow)
        self.min_sigma = float(min_sigma)
        self.set_covariance(np.eye(3) * min_sigma ** 2)

    def set_covariance(self, cov: np.ndarray) -> None:
        cov = np.asarray(cov, dtype=np.float64) + np.eye(3) * self.min_sigma ** 2 * 0.25
        self.cov = cov
        self.inv = np.linalg.inv(cov)

    def fit_noise(self, images, quantile: float = 11.34) -> None:
        """Estimate the per-camera colour covariance from frames (BGR, at the model's
        size) against the mean: the median absolute deviation per channel first, then
        three times the covariance of the pixels with ``d_M`` at most ``quantile`` (the
        99 % chi-square(3) quantile)."""
        res = np.concatenate([(cv2.cvtColor(im, cv2.COLOR_BGR2YUV).astype(np.float32) - self.mean).reshape(-1, 3)
                              for im in images])
        # start from the median absolute deviation per channel (people and their shadows
        # may cover a good part of the frames), then the covariance of what it keeps
        mad = 1.4826 * np.median(np.abs(res), axis=0)
        self.set_covariance(np.diag(np.maximum(mad, 0.5) ** 2))
        for _ in range(3):
            d = np.einsum("ni,ij,nj->n", res, self.inv, res)
            r = res[d <= quantile]
            self.set_covariance((r.T @ r) / max(1, len(r) - 1) / 0.92)   # 0.92: the variance a 99 % cut keeps

    def distance(self, image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Squared Mahalanobis distance (H, W) float32 of a BGR frame at the model's size."""
        yuv = cv2.cvtColor(image, cv2.COLOR_BGR2YUV).astype(np.float32)
        if out is None:
            out = np.empty(yuv.shape[:2], dtype=np.float32)
        _mahalanobis(yuv, self.mean, self.inv.astype(np.float32), np.float32(self.shadow), out)
        return out
