"""Bilinear lookups of an image at many scattered points, in as few ``cv2.remap`` calls as fit.

Why: ``cv2.remap`` is OpenCV's bilinear sampler and several times faster than scipy's
``map_coordinates`` or a numpy gather (the halo test: 1.5-1.8 against 11.5 ms a lookup of
21-22k points x 7; the synthetic renderer serves every texture sample of a frame with it).
Its maps are images, each side below 32767, so the points are laid out in rows of
``ROW_WIDTH`` and sent in calls of at most ``MAX_ROWS`` rows. OpenCV 5 weighs the four pixels
exactly (earlier versions in 1/32 px steps; the halo test's torch twin, ``fusion/occlusion_gpu.py``,
relies on it); borders are replicated.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Points a map row holds.
ROW_WIDTH = 1024
#: Rows one call takes (below OpenCV's 32767): 32M points a call, more in several.
MAX_ROWS = 32000


def bilinear_at(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Float32 samples of ``image`` (HxW or HxWxC, C <= 4) at pixel coordinates ``(x, y)``
    (any shape, the same for both): shape ``x.shape`` (+ ``(C,)``)."""
    src = np.ascontiguousarray(image, dtype=np.float32)
    channels = src.shape[2:]
    flat_x = np.asarray(x, dtype=np.float32).ravel()
    flat_y = np.asarray(y, dtype=np.float32).ravel()
    n = flat_x.size
    if n == 0:
        return np.zeros((*np.shape(x), *channels), dtype=np.float32)
    chunk = ROW_WIDTH * MAX_ROWS
    parts = [_one_call(src, flat_x[i : i + chunk], flat_y[i : i + chunk]) for i in range(0, n, chunk)]
    out = parts[0] if len(parts) == 1 else np.concatenate(parts)
    return out.reshape((*np.shape(x), *channels))


def _one_call(src: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """One ``cv2.remap`` call: the 1-D coordinates padded to whole rows of ``ROW_WIDTH``."""
    n = x.size
    rows = -(-n // ROW_WIDTH)
    maps = np.zeros((2, rows * ROW_WIDTH), dtype=np.float32)
    maps[0, :n], maps[1, :n] = x, y
    shape = (rows, ROW_WIDTH)
    out = cv2.remap(
        src, maps[0].reshape(shape), maps[1].reshape(shape), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.reshape((rows * ROW_WIDTH, *src.shape[2:]))[:n]
