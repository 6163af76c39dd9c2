"""Which of turn, rescale and crop makes a calibrated camera fit a video of another size,
decided from the two sizes (and, where the video is the larger, from a padding band in its
frames), with one sentence saying what was chosen and why (``smartroom calibrate fit``).

The rule, for a calibrated image of ``w0 x h0`` and a video of ``w x h``:

1. the same size: nothing to do;
2. one portrait and the other landscape: a quarter **turn** first, in the direction that
   stands the room upright in the video (the world's up points up in the turned image),
   else 90 degrees, said; then the rest of the rule on the turned size;
3. one side equal and the other at most 16 pixels off: a **crop** (a window of the
   calibrated image; a padding when the video is the larger): the focal length stays and
   the principal point moves by the window's offset (where the band lies: see below);
4. both sides scaled by one factor (each side within a pixel of the other side's factor):
   a **rescale** about the image corner (``Camera.scaled``);
5. both sides different, one side's factor explaining it up to a crop of at most 16
   pixels of the calibrated image in the other side: a rescale by that factor, then that
   crop (a 960x540 proxy of a 1920x1088 image);
6. anything else is not guessed: the camera is left undecided for ``--rescale`` or
   ``--crop``.

Where the rows (columns) that differ lie, the *placement*: ``end`` (at the bottom, or the
right: codecs pad 1080 rows to 1088 there, so the principal point stays), ``centre``
(half on each side: the principal point moves by half the difference) or ``start`` (top,
or left). It is the user's when given; else, when the video is the larger, it is read from
a band of one colour (black bars, a codec's grey) in the video's frames; else it is assumed: a
difference of at most 16 pixels is a codec's padding (``end``), a larger one a centred
sensor crop or letterbox (``centre``). A video smaller than its calibration cannot show
where its missing rows were, so there the assumption is all there is, and it is said.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np

from calibration.camera import Camera
from calibration.transform import cropped, turned

__all__ = ["Fitted", "fit_camera", "padding_placement", "turn_direction", "PLACEMENTS", "CODEC_PADDING"]

#: the most pixels a codec pads a side to (a multiple of 16: 1080 -> 1088), and the largest
#: difference rules 3 and 5 take for a crop without being told
CODEC_PADDING = 16

#: user words for a placement -> the placement (``bottom`` also means right, ``top`` left)
PLACEMENTS = {"bottom": "end", "right": "end", "top": "start", "left": "start", "centre": "centre",
              "center": "centre", "topleft": "end"}  # topleft: the old --anchor, the window at the top-left

#: a band is padding when its rows are of one colour: their grey levels' standard deviation
#: along the row under this (median over the frames; codec noise stays below it)
FLAT = 3.0


@dataclass(frozen=True)
class Fitted:
    """A camera fitted to a video: ``said`` is one line naming the camera, what was done
    and why; ``decided`` is False when the sizes did not say which fit (camera unchanged)."""

    camera: Camera
    said: str
    changed: bool
    decided: bool = True


# -- the turn ------------------------------------------------------------------------------

def _up_in_image(camera: Camera) -> float | None:
    """How upright the world's up is in the camera's image at its principal point: 1 straight
    up, -1 straight down, 0 sideways; None for a camera looking straight up or down."""
    axis = camera.R[2]  # the optical axis in world coordinates
    if abs(axis[2]) > 0.95:
        return None
    p = camera.centre + 3.0 * axis
    uv = camera.project(np.array([p, p + [0.0, 0.0, 0.1]]))
    d = uv[1] - uv[0]
    n = float(np.hypot(d[0], d[1]))
    if not np.isfinite(n) or n == 0:
        return None
    return float(-d[1] / n)


def turn_direction(camera: Camera) -> tuple[int, str]:
    """The clockwise quarter turn (90 or 270) that stands the room upright in the turned
    image, and why (or 90 and why it could not be told)."""
    up = {deg: _up_in_image(turned(camera, deg)) for deg in (90, 270)}
    if up[90] is None:
        return 90, "the camera looks straight down or up, so its image has no up: 90 assumed, --turn 270 otherwise"
    best = max(up, key=up.get)
    if up[best] > 0.7:
        return best, f"it stands the room upright in the video; --turn {360 - best} for the other way"
    return 90, ("neither quarter turn stands the room upright (the calibrated image is already upright): "
                "90 assumed, --turn 270 otherwise")


# -- the padding band ----------------------------------------------------------------------

def _grey(frames) -> np.ndarray:
    return np.stack([(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) if f.ndim == 3 else f).astype(np.float32)
                     for f in frames])


def _spread(grey: np.ndarray, row: int) -> float:
    """The spread of grey levels along a row (median over the frames)."""
    return float(np.median(grey[:, row, :].std(axis=1)))


def _flat(grey: np.ndarray, rows) -> bool:
    """A band of one colour: its outermost row (``rows[0]``) and most of its rows flat (a
    codec smears the image into the band's inner rows)."""
    rows = list(rows)
    return bool(rows) and _spread(grey, rows[0]) < FLAT and np.median([_spread(grey, r) for r in rows]) < FLAT


def padding_placement(frames: Sequence[np.ndarray], axis: int, extra: int) -> tuple[str | None, str]:
    """Where a video pads ``extra`` rows (``axis`` 0) or columns (``axis`` 1) its calibrated
    image, read from a band of one colour in ``frames`` (images of the video): ``end``, ``start``,
    ``centre``, or None when no band or more than one fits; and a phrase saying what was seen."""
    what, ends = ("rows", ("top", "bottom")) if axis == 0 else ("columns", ("left", "right"))
    if not len(frames) or extra <= 0:
        return None, "no frames to look at"
    grey = _grey(frames)
    if axis == 1:
        grey = grey.transpose(0, 2, 1)
    n = grey.shape[1]
    if extra >= n // 2:
        return None, f"{extra} {what} of {n} is no padding band"
    half = extra // 2
    flat = {
        "end": _flat(grey, range(n - 1, n - extra - 1, -1)),
        "start": _flat(grey, range(0, extra)),
        "centre": extra >= 2 and _flat(grey, range(0, half)) and _flat(grey, range(n - 1, n - extra + half - 1, -1)),
    }
    inner = range(extra + 1, n - extra - 1, max(1, (n - 2 * extra) // 32))
    texture = np.median([_spread(grey, r) for r in inner]) if len(inner) else 0.0
    if texture < 2 * FLAT:
        return None, "the frames are too plain to show a padding band"
    found = [p for p, ok in flat.items() if ok]
    where = {"end": f"at the {ends[1]}", "start": f"at the {ends[0]}", "centre": f"split {ends[0]} and {ends[1]}"}
    if len(found) == 1:
        return found[0], f"a band of {extra} {what} of one colour {where[found[0]]} of the video"
    if not found:
        return None, f"no band of {extra} {what} of one colour at the video's edges"
    return None, f"bands of one colour fit {' and '.join(where[p] for p in found)}"


# -- the fit -------------------------------------------------------------------------------

def _scaled(camera: Camera, s: float, width: int, height: int) -> Camera:
    """The camera imaging at ``s`` times its size (about the image corner), cut to ``width x height``."""
    K = camera.K.copy()
    K[0, 0] *= s
    K[0, 1] *= s
    K[1, 1] *= s
    K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return Camera(camera.name, int(width), int(height), K, camera.dist.copy(), camera.R.copy(), camera.t.copy())


def _offset(diff: float, placement: str) -> float:
    """The window's first row (column) for ``diff`` more calibrated than video rows."""
    if placement == "end":
        return 0.0
    if placement == "start":
        return float(diff)
    return float(int(diff / 2)) if float(diff).is_integer() else diff / 2


def _num(v: float) -> str:
    v = float(v) + 0.0  # no "-0"
    return f"{v:g}" if v.is_integer() else f"{v:.2f}"


def _place(sizes, video, scale, given, frames) -> tuple[dict, str]:
    """The placement of each side that differs, and why."""
    names = {0: ("rows", "bottom", "top"), 1: ("columns", "right", "left")}
    out, why = {}, []
    for axis, (n0, n) in ((1, (sizes[0], video[0])), (0, (sizes[1], video[1]))):
        diff = n0 * scale - n
        if abs(diff) < 1e-9:
            continue
        what, end, start = names[axis]
        count = f"{_num(abs(diff))} {what} {'fewer' if diff > 0 else 'more'} in the video"
        words = {"end": f"at the {end}", "start": f"at the {start}", "centre": "centred"}
        if given:
            out[axis] = given
            why.append(f"{count}, {words[given]} as given")
            continue
        if diff < 0 and frames is not None:
            placement, seen = padding_placement(frames(), axis, int(round(-diff)))
            if placement:
                out[axis] = placement
                why.append(f"{count}, {words[placement]}: {seen}")
                continue
        else:
            seen = "a smaller video cannot show where" if diff > 0 else "no frames looked at"
        if abs(diff) / scale <= CODEC_PADDING:
            out[axis] = "end"
            why.append(f"{count}, assumed {words['end']} as codecs pad there to a multiple of 16 ({seen}; "
                       f"--crop centre or --crop {start} otherwise)")
        else:
            out[axis] = "centre"
            why.append(f"{count}, assumed centred as sensor crops and letterboxes are ({seen}; "
                       f"--crop {end} or --crop {start} otherwise)")
    return out, "; ".join(why)


def _crop(camera: Camera, scale: float, width: int, height: int, given, frames, how: str) -> tuple[Camera, str]:
    """Rescale by ``scale`` (when not 1), then take the ``width x height`` window."""
    sizes = (camera.width, camera.height)
    placement, why = _place(sizes, (width, height), scale, given, frames)
    sw, sh = sizes[0] * scale, sizes[1] * scale
    left = _offset(sw - width, placement.get(1, "end"))
    top = _offset(sh - height, placement.get(0, "end"))
    said = []
    c = camera
    if scale != 1.0:
        c = _scaled(camera, scale, width, height)
        said.append(f"rescaled {sizes[0]}x{sizes[1]} -> {_num(sw)}x{_num(sh)} (x{scale:.4f}), then")
    c = cropped(c, left, top, width, height)
    verb = "padded" if (sw <= width and sh <= height) else "cropped"
    moved = "principal point kept" if left == 0 and top == 0 else \
        f"principal point moved by ({_num(-left)}, {_num(-top)}) px"
    said.append(f"{verb} {_num(sw)}x{_num(sh)} -> {width}x{height} at offset ({_num(left)}, {_num(top)}), {moved}: "
                + (f"{how}; {why}" if how else why))
    return c, " ".join(said)


def _explained_by_one_scale(w0, h0, w, h) -> tuple[float, float] | None:
    """Rule 5: the factor of one side and the crop (in calibrated pixels) it leaves in the other."""
    best = None
    for s, rest in ((w / w0, abs(h0 * w / w0 - h) * w0 / w), (h / h0, abs(w0 * h / h0 - w) * h0 / h)):
        if rest <= CODEC_PADDING and (best is None or rest < best[1]):
            best = (s, rest)
    return best


def _once(get):
    kept = []

    def frames():
        if not kept:
            kept.append(list(get()))
        return kept[0]
    return frames


def fit_camera(camera: Camera, width: int, height: int, mode: str | None = None, turn: int | None = None,
               placement: str | None = None,
               frames: Callable[[], Sequence[np.ndarray]] | None = None) -> Fitted:
    """``camera`` fitted to a ``width x height`` video by the rule in the module's docstring.

    ``mode`` (``rescale`` or ``crop``) and ``turn`` (90, 180, 270: 90 and 270 apply where the
    video is turned a quarter, 180 to every camera) are the user's overrides; ``placement``
    (``end``, ``start``, ``centre``) says where a crop lies; ``frames`` gives a few images of
    the video, asked for only when a padding band is looked for."""
    c, name = camera, camera.name
    if frames is not None:
        frames = _once(frames)
    said, changed = [], False
    w0, h0 = c.width, c.height
    quarter = w0 != h0 and width != height and (w0 > h0) != (width > height)
    if quarter or (turn is not None and turn % 360 == 180):
        if turn is not None:
            deg, why = turn % 360, f"--turn {turn} given"
        else:
            deg, why = turn_direction(c)
            why = f"the video is {'portrait' if height > width else 'landscape'}, the calibration not; {why}"
        c = turned(c, deg)
        changed = True
        said.append(f"turned {deg} degrees clockwise, {w0}x{h0} -> {c.width}x{c.height} ({why})")
    w0, h0 = c.width, c.height
    if (w0, h0) == (width, height):
        if not said:
            return Fitted(c, f"{name}: {width}x{height}, fits", False)
        return Fitted(c, f"{name}: " + ", then ".join(said), changed)
    sx, sy = width / w0, height / h0
    if mode == "rescale":
        aspect = "" if abs(sx / sy - 1) < 0.01 else \
            f"; the aspect ratio changes by {100 * (sx / sy - 1):+.1f} %: is it a crop?"
        c = c.scaled(width, height)
        said.append(f"rescaled {w0}x{h0} -> {width}x{height} (x{sx:.4f}, x{sy:.4f}; --rescale given{aspect})")
    elif mode == "crop":
        c, text = _crop(c, 1.0, width, height, placement, frames, "--crop given")
        said.append(text)
    elif (w0 == width or h0 == height) and abs(w0 - width) + abs(h0 - height) <= CODEC_PADDING:
        c, text = _crop(c, 1.0, width, height, placement, frames, "")
        said.append(text)
    elif w0 != width and h0 != height and abs(w0 * sy - width) <= 1 and abs(h0 * sx - height) <= 1:
        c = c.scaled(width, height)
        said.append(f"rescaled {w0}x{h0} -> {width}x{height} (x{sx:.4f}, x{sy:.4f}: one factor for both sides, "
                    "the same image scaled)")
    elif w0 != width and h0 != height and (one := _explained_by_one_scale(w0, h0, width, height)):
        c, text = _crop(c, one[0], width, height, placement, frames,
                        "one factor for one side, a few pixels off in the other")
        said.append(text)
    else:
        said.append(f"not changed: {w0}x{h0} (aspect {w0 / h0:.3f}) against a {width}x{height} video "
                    f"(aspect {width / height:.3f}) is neither one scale factor nor a crop of a few pixels; "
                    "say which with --rescale or --crop [bottom|top|centre]")
        return Fitted(c, f"{name}: " + ", then ".join(said), changed, decided=False)
    return Fitted(c, f"{name}: " + ", then ".join(said), True)
