"""Text on images (PNG checks, previews, the viewer's labels) that stays readable on any
background: letters with a dark outline around them.

OpenCV's ``putText`` advances each letter by an amount that grows with the stroke's
thickness, so the usual trick (the same text drawn twice, thick and dark then thin and
light) puts the outline's letters further apart than the text's: a ghost beside every
word. Here the outline is the text's own stroke, grown (a dilation), so it is exactly
around the letters.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["outlined_text", "FONT"]

FONT = cv2.FONT_HERSHEY_SIMPLEX


def outlined_text(img: np.ndarray, text: str, org, scale: float, colour, thickness: int = 1, outline: int = 2,
                  outline_colour=(0, 0, 0), font: int = FONT) -> np.ndarray:
    """Draw ``text`` with its baseline starting at ``org`` onto ``img`` (BGR or BGRA,
    uint8, changed in place and returned), in ``colour`` with an ``outline`` pixels wide
    border in ``outline_colour`` (colours given in the image's channel order; a BGRA
    image's alpha is set where anything is drawn)."""
    x, y = int(round(org[0])), int(round(org[1]))
    (w, h), base = cv2.getTextSize(text, font, scale, thickness)
    pad = outline + thickness + 2
    x0, y0 = max(0, x - pad), max(0, y - h - pad)
    x1, y1 = min(img.shape[1], x + w + pad), min(img.shape[0], y + base + pad)
    if x1 <= x0 or y1 <= y0:
        return img
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.putText(mask, text, (x - x0, y - y0), font, scale, 255, thickness, cv2.LINE_AA)
    size = 2 * outline + 1
    ring = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))) if outline > 0 else mask
    region = img[y0:y1, x0:x1]
    channels = region.shape[2] if region.ndim == 3 else 1
    for layer, colour_of in ((ring, outline_colour), (mask, colour)):
        a = (layer.astype(np.float32) / 255.0)[..., None]
        c = np.asarray(colour_of, np.float32).reshape(-1)
        if channels == 4 and c.size == 3:
            c = np.append(c, 255.0)
        if region.ndim == 2:
            a, c = a[..., 0], c[0]
        blended = region.astype(np.float32) * (1.0 - a) + c[:channels] * a if region.ndim == 3 else \
            region.astype(np.float32) * (1.0 - a) + c * a
        region[...] = np.clip(np.round(blended), 0, 255).astype(np.uint8)
    return img
