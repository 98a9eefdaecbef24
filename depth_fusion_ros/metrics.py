"""Depth error metrics of the paper (§IV) and the modern standard ones (no ROS).

All metrics are computed on valid ground-truth pixels (finite and > 0) where the
prediction is finite. Predictions made at the working resolution are upsampled to the
ground-truth resolution first, as the paper does (320x240 -> 640x480).

Per sequence, pixel-wise metrics (MAE, RMSE, AbsRel, delta<1.25) are pooled over all pixels
of all frames; medians use an even sample of at most ``SAMPLES_PER_FRAME`` pixels per frame;
the scale-invariant error is scale-invariant per image, so it is the mean of its per-frame
values.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

#: Normalised grey-gradient threshold between high- and low-gradient pixels (paper Table I).
GRADIENT_THRESHOLD = 0.35
#: Smallest depth used inside logarithms (m), so a zero prediction cannot give -inf.
LOG_EPS = 1e-3
#: Per-frame pixels kept for medians, box plots and histograms. Sums stay exact; the kept
#: pixels are an even stride through the valid ones, so memory is bounded per frame.
SAMPLES_PER_FRAME = 10000


def upsample_depth(pred: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a prediction to the ground-truth grid.

    Dense predictions are interpolated bilinearly (the paper's upsampling); predictions
    with holes (NaN) use nearest-neighbour so a hole never bleeds into its neighbours.
    """
    pred = np.asarray(pred, dtype=np.float32)
    if pred.shape == (height, width):
        return pred
    interp = cv2.INTER_LINEAR if np.all(np.isfinite(pred)) else cv2.INTER_NEAREST
    return cv2.resize(pred, (width, height), interpolation=interp)


def valid_mask(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Pixels where both ground truth (finite, > 0) and prediction (finite) exist."""
    return np.isfinite(gt) & (gt > 0) & np.isfinite(pred)


def normalised_gradient(gray: np.ndarray) -> np.ndarray:
    """Grey-gradient magnitude normalised to [0, 1] (1 = the strongest edge in the image).

    ``gray`` is float in [0, 1]. Sobel derivatives; normalising by the image's own maximum
    makes the 0.35 threshold of the paper independent of contrast and resolution.
    """
    gx = cv2.Sobel(gray.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray.astype(np.float32), cv2.CV_32F, 0, 1, ksize=3)
    mag = np.sqrt(gx * gx + gy * gy)
    peak = float(mag.max())
    return mag / peak if peak > 0 else mag


def high_gradient_mask(gray: np.ndarray, threshold: float = GRADIENT_THRESHOLD) -> np.ndarray:
    """Pixels whose normalised grey gradient is at least ``threshold``."""
    return normalised_gradient(gray) >= threshold


#: ``good_density``: estimates within this relative error of the ground truth count as good.
GOOD_ABS_REL = 0.10


def good_density(pred: np.ndarray, gt: np.ndarray, max_abs_rel: float = GOOD_ABS_REL) -> float:
    """Fraction of *all* pixels holding an estimate within ``max_abs_rel`` of valid ground truth.

    Density and accuracy of a semi-dense method in one number (issue 11: "density of
    multi-view estimates with AbsRel <= 10 %"): it cannot be raised by publishing more wrong
    points, nor kept by publishing fewer right ones. Pixels without ground truth count as
    not good. ``pred`` and ``gt`` have the same shape (upsample first).
    """
    valid = np.isfinite(pred) & np.isfinite(gt) & (gt > 0)
    good = np.zeros(gt.shape, dtype=bool)
    good[valid] = np.abs(pred[valid] - gt[valid]) <= max_abs_rel * gt[valid]
    return float(good.mean())


def frame_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Metrics of one depth image against ground truth of the same shape."""
    acc = MetricAccumulator()
    acc.add(pred, gt, mask)
    return acc.summary()


@dataclass
class MetricAccumulator:
    """Pools per-pixel errors over frames; ``summary()`` gives the sequence metrics."""

    n: int = 0
    sum_abs: float = 0.0
    sum_sq: float = 0.0
    sum_abs_rel: float = 0.0
    n_delta1: int = 0
    si_per_frame: list[float] = field(default_factory=list)
    mae_per_frame: list[float] = field(default_factory=list)
    samples_per_frame: int = SAMPLES_PER_FRAME
    abs_rel_values: list[np.ndarray] = field(default_factory=list)
    err_values: list[np.ndarray] = field(default_factory=list)

    def add(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> int:
        """Add one frame; returns how many pixels it contributed (0 adds a NaN frame MAE)."""
        if pred.shape != gt.shape:
            raise ValueError(f'prediction {pred.shape} and ground truth {gt.shape} differ in shape')
        m = valid_mask(pred, gt)
        if mask is not None:
            m &= mask
        y = gt[m].astype(np.float64)
        p = pred[m].astype(np.float64)
        if y.size == 0:
            self.mae_per_frame.append(float('nan'))
            return 0
        err = p - y
        abs_err = np.abs(err)
        self.n += y.size
        self.sum_abs += float(abs_err.sum())
        self.sum_sq += float((err * err).sum())
        abs_rel = abs_err / y
        self.sum_abs_rel += float(abs_rel.sum())
        ratio = np.maximum(p / y, y / np.maximum(p, LOG_EPS))
        self.n_delta1 += int(np.count_nonzero(ratio < 1.25))
        d = np.log(y) - np.log(np.maximum(p, LOG_EPS))
        self.si_per_frame.append(float(np.mean(d * d) - np.mean(d) ** 2))
        self.mae_per_frame.append(float(abs_err.mean()))
        step = max(1, -(-y.size // self.samples_per_frame))
        self.abs_rel_values.append(abs_rel[::step].astype(np.float32))
        self.err_values.append(err[::step].astype(np.float32))
        return int(y.size)

    def signed_errors(self) -> np.ndarray:
        """Sampled signed errors ``prediction - ground truth`` (m) of all frames (histograms)."""
        return np.concatenate(self.err_values) if self.err_values else np.zeros(0, np.float32)

    def errors(self) -> np.ndarray:
        """Sampled absolute errors (m) of all frames (box plots, medians)."""
        return np.abs(self.signed_errors())

    def summary(self) -> dict[str, float]:
        if self.n == 0:
            nan = float('nan')
            return {
                'mae': nan,
                'rmse': nan,
                'si': nan,
                'abs_rel': nan,
                'delta1': nan,
                'median_abs_rel': nan,
                'median_abs_err': nan,
                'n_pixels': 0,
            }
        return {
            'mae': self.sum_abs / self.n,
            'rmse': float(np.sqrt(self.sum_sq / self.n)),
            'si': float(np.mean(self.si_per_frame)),
            'abs_rel': self.sum_abs_rel / self.n,
            'delta1': self.n_delta1 / self.n,
            'median_abs_rel': float(np.median(np.concatenate(self.abs_rel_values))),
            'median_abs_err': float(np.median(self.errors())),
            'n_pixels': int(self.n),
        }
