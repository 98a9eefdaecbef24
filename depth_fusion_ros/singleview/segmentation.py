"""SLIC-style superpixels (colour + position k-means) with numpy and OpenCV only.

The simulated CNN prior needs image segments that follow colour edges, because a CNN's
depth errors are shared by the pixels of one image structure (paper §III, Fig. 2). This is
Achanta et al.'s SLIC (TPAMI 2012) without the connectivity post-pass: centres start on a
regular grid, and each pixel is assigned to the nearest of the 9 centres seeded in its own
and the 8 neighbouring grid cells, with the distance

    D² = ‖Lab_p − Lab_c‖² + (compactness / S)² ‖xy_p − xy_c‖²      (S = grid step in px)

then centres move to their pixels' mean; a few iterations converge. Everything is a
vectorised (9, H, W) array operation, so a 320x240 image takes a few milliseconds.
"""

from __future__ import annotations

import cv2
import numpy as np


def grid_shape(height: int, width: int, n_segments: int) -> tuple[int, int]:
    """Rows and columns of seed cells giving about ``n_segments`` square-ish cells."""
    step = np.sqrt(height * width / max(1, n_segments))
    return max(1, round(height / step)), max(1, round(width / step))


def slic_superpixels(
    rgb: np.ndarray,
    n_segments: int = 24,
    compactness: float = 20.0,
    iterations: int = 6,
    max_pixels: int = 160 * 120,
) -> np.ndarray:
    """(H, W) int32 labels ``0..K-1`` of about ``n_segments`` colour-coherent segments.

    ``compactness`` trades colour against position (Lab units per grid step): low values
    follow colour edges closely, high values give grid-like cells. Images larger than
    ``max_pixels`` are segmented at a reduced size and the labels upsampled (nearest): the
    segments are tens of pixels wide, so this costs little accuracy and saves most of the time.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f'slic_superpixels needs an HxWx3 uint8 RGB image, got {rgb.shape} {rgb.dtype}')
    if n_segments < 1:
        raise ValueError(f'n_segments must be >= 1, got {n_segments}')
    h, w = rgb.shape[:2]
    if h * w > max_pixels:
        f = np.sqrt(max_pixels / (h * w))
        small = cv2.resize(rgb, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
        labels = slic_superpixels(small, n_segments, compactness, iterations, max_pixels)
        labels = cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)
        return np.unique(labels, return_inverse=True)[1].reshape(h, w).astype(np.int32)
    lab = cv2.cvtColor(rgb.astype(np.float32) / 255.0, cv2.COLOR_RGB2LAB)  # L 0..100, a/b ±127
    rows, cols = grid_shape(h, w, n_segments)
    cell_h, cell_w = h / rows, w / cols
    step = float(np.sqrt(cell_h * cell_w))
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    # Features: Lab and position scaled so that one grid step weighs `compactness` Lab units.
    pos_weight = compactness / step
    feats = np.concatenate((lab, (u * pos_weight)[..., None], (v * pos_weight)[..., None]), axis=2)

    cy = (np.arange(rows) + 0.5) * cell_h
    cx = (np.arange(cols) + 0.5) * cell_w
    gy, gx = np.meshgrid(cy, cx, indexing='ij')
    seeds = np.stack((gy.round().astype(int).clip(0, h - 1), gx.round().astype(int).clip(0, w - 1)), -1)
    centres = feats[seeds[..., 0], seeds[..., 1]].reshape(-1, 5).astype(np.float64)

    # Candidate centres of every pixel: its own seed cell and the 8 around it.
    pr = np.minimum((v / cell_h).astype(int), rows - 1)
    pc = np.minimum((u / cell_w).astype(int), cols - 1)
    cand, ok = [], []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = pr + dr, pc + dc
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            cand.append(np.where(inside, r.clip(0, rows - 1) * cols + c.clip(0, cols - 1), 0))
            ok.append(inside)
    cand_idx = np.stack(cand)  # (9, H, W)
    cand_ok = np.stack(ok)

    chans = [np.ascontiguousarray(feats[..., k]) for k in range(5)]
    labels = cand_idx[4]
    for _ in range(iterations):
        best = np.full((h, w), np.inf, np.float32)
        for j in range(9):
            dist = np.zeros((h, w), np.float32)
            for k in range(5):
                diff = centres[:, k].astype(np.float32)[cand_idx[j]] - chans[k]
                dist += diff * diff
            dist[~cand_ok[j]] = np.inf
            closer = dist < best
            best[closer] = dist[closer]
            labels = np.where(closer, cand_idx[j], labels)
        flat_labels = labels.ravel()
        counts = np.bincount(flat_labels, minlength=len(centres))
        has = counts > 0
        for k in range(5):
            sums = np.bincount(flat_labels, chans[k].ravel(), minlength=len(centres))
            centres[has, k] = sums[has] / counts[has]
    _, relabelled = np.unique(labels, return_inverse=True)
    return relabelled.reshape(h, w).astype(np.int32)
