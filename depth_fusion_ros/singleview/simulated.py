"""A simulated single-view CNN prior with the error structure the paper describes (§III, Fig. 2).

It exists to measure the *fusion* independently of network quality: an evaluation-only
``single_view`` source built from the ground truth, never a stand-in for the network in
the nodes. The paper observes that single-view errors are locally, not globally,
correlated: the error histogram has one mode per image segment. So, from the ground-truth
depth ``z`` (holes filled with the nearest valid depth, so the prior is dense like a CNN)
and the RGB image:

    s(p) = max(min_depth, blur(z)(p) · g · (1 + e[k(p)]) · (1 + D(p)) · (1 + n(p)) + o[k(p)])

* ``k(p)``: SLIC superpixel of ``p`` on colour + position (``n_segments``, ``compactness``);
* ``e[k] ~ N(0, segment_scale_sigma)`` and ``o[k] ~ N(0, segment_offset_sigma)`` metres:
  each segment's own scale error and offset (clipped to ±``clip_sigmas`` σ);
* ``g = 1 + N(0, global_scale_sigma)``: the image-wide scale error of a monocular network;
* ``D``: a smooth low-frequency deformation, a ``deformation_cells``-wide grid of
  ``N(0, deformation_sigma)`` values upsampled bicubically to the image;
* ``n(p) ~ N(0, noise_sigma)``: independent per-pixel noise;
* ``blur``: a Gaussian of ``blur_px`` pixels, the loss of detail of a low-resolution output.

Defaults give a single-view MAE of about 0.2–0.4 m on indoor scenes at 1–4 m, like the
paper's Eigen column (0.23–0.32 m on TUM). Every draw comes from
``numpy.random.default_rng(seed)``; the evaluation seeds it with ``(options.seed, frame
index)`` so results are reproducible frame by frame.

``to_relative_inverse`` turns it into what a disparity network gives: inverse depth with an
unknown positive scale and shift per image (``--single-view simulated_relative``), so the
fusion's alignment of relative models is measured against the same prior made metric.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scipy import ndimage

from .segmentation import slic_superpixels


@dataclass
class SimulatedPriorConfig:
    """Parameters of the simulated prior (see the module docstring for the model)."""

    n_segments: int = 24
    compactness: float = 20.0
    segment_scale_sigma: float = 0.2
    segment_offset_sigma: float = 0.08
    global_scale_sigma: float = 0.1
    deformation_sigma: float = 0.06
    deformation_cells: int = 4
    noise_sigma: float = 0.01
    blur_px: float = 1.0
    clip_sigmas: float = 2.5
    min_depth: float = 0.1

    def validate(self) -> None:
        for name, value in asdict(self).items():
            if not np.isfinite(value) or value < 0:
                raise ValueError(f'simulated prior: {name} must be a finite number >= 0, got {value}')
        if self.n_segments < 1 or self.deformation_cells < 1:
            raise ValueError('simulated prior: n_segments and deformation_cells must be >= 1')
        if self.min_depth <= 0:
            raise ValueError(f'simulated prior: min_depth must be positive, got {self.min_depth}')

    @classmethod
    def from_dict(cls, data: dict) -> SimulatedPriorConfig:
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f'simulated prior: unknown parameter(s) {unknown}; known: {sorted(known)}')
        cfg = cls(**data)
        cfg.validate()
        return cfg


@dataclass
class SimulatedPrediction:
    """The simulated depth and every ingredient, so tests can check the statistics."""

    depth: np.ndarray  # (H, W) float32 metres, dense
    segments: np.ndarray  # (H, W) int32 labels
    segment_scale: np.ndarray  # (K,) e[k]
    segment_offset: np.ndarray  # (K,) o[k] metres
    global_scale: float  # g
    deformation: np.ndarray  # (H, W) D
    noise: np.ndarray  # (H, W) n
    base_depth: np.ndarray  # (H, W) filled and blurred ground truth


def fill_holes(depth: np.ndarray) -> np.ndarray:
    """Replace invalid pixels (NaN, <= 0) by the nearest valid depth; ValueError if none is valid."""
    valid = np.isfinite(depth) & (depth > 0)
    if valid.all():
        return depth.astype(np.float32)
    if not valid.any():
        raise ValueError('simulated prior: the ground-truth depth has no valid pixel')
    idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return depth[idx[0], idx[1]].astype(np.float32)


def smooth_field(shape: tuple[int, int], cells: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Low-frequency random field: a ``cells``-wide grid of N(0, σ) values, bicubic upsampling."""
    h, w = shape
    gh = max(2, round(cells * h / w) + 1)
    gw = cells + 1
    grid = rng.normal(0.0, sigma, size=(gh, gw)).astype(np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def simulate_prior(
    gt_depth: np.ndarray,
    rgb: np.ndarray,
    config: SimulatedPriorConfig | None = None,
    seed: int | tuple[int, ...] = 0,
) -> SimulatedPrediction:
    """Simulated single-view depth for one image (``gt_depth`` and ``rgb`` at one resolution;
    ``rgb`` is resized to the depth's size if they differ)."""
    cfg = config or SimulatedPriorConfig()
    cfg.validate()
    gt_depth = np.asarray(gt_depth, dtype=np.float32)
    if gt_depth.ndim != 2:
        raise ValueError(f'simulated prior: depth must be HxW, got shape {gt_depth.shape}')
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f'simulated prior: rgb must be HxWx3 uint8, got {rgb.shape} {rgb.dtype}')
    h, w = gt_depth.shape
    if rgb.shape[:2] != (h, w):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(seed)

    base = fill_holes(gt_depth)
    if cfg.blur_px > 0:
        base = cv2.GaussianBlur(base, (0, 0), cfg.blur_px)
    segments = slic_superpixels(rgb, cfg.n_segments, cfg.compactness)
    k = int(segments.max()) + 1
    lim = cfg.clip_sigmas if cfg.clip_sigmas > 0 else np.inf
    seg_scale = np.clip(rng.normal(0, 1, k), -lim, lim) * cfg.segment_scale_sigma
    seg_offset = np.clip(rng.normal(0, 1, k), -lim, lim) * cfg.segment_offset_sigma
    global_scale = 1.0 + float(np.clip(rng.normal(), -lim, lim)) * cfg.global_scale_sigma
    deformation = smooth_field((h, w), cfg.deformation_cells, cfg.deformation_sigma, rng)
    noise = rng.normal(0.0, cfg.noise_sigma, size=(h, w)).astype(np.float32)

    depth = base * global_scale * (1 + seg_scale[segments]) * (1 + deformation) * (1 + noise)
    depth = np.maximum(depth + seg_offset[segments], cfg.min_depth).astype(np.float32)
    return SimulatedPrediction(
        depth=depth,
        segments=segments,
        segment_scale=seg_scale.astype(np.float32),
        segment_offset=seg_offset.astype(np.float32),
        global_scale=global_scale,
        deformation=deformation,
        noise=noise,
        base_depth=base,
    )


class SimulatedPrior:
    """``simulate_prior`` with a fixed configuration: ``predict(gt_depth, rgb, seed)``.

    Unlike a ``DepthPredictor`` it needs the ground truth, which is why it is an evaluation
    source only.
    """

    output_kind = 'metric_depth'

    def __init__(self, config: SimulatedPriorConfig | None = None):
        self.config = config or SimulatedPriorConfig()
        self.config.validate()

    def predict(self, gt_depth: np.ndarray, rgb: np.ndarray, seed: int | tuple[int, ...] = 0) -> np.ndarray:
        return simulate_prior(gt_depth, rgb, self.config, seed).depth


@dataclass
class RelativeInverse:
    """A metric depth turned into inverse depth with an unknown positive scale and shift."""

    inverse: np.ndarray  # (H, W) float32, scale / depth + shift
    scale: float
    shift: float


def to_relative_inverse(
    depth: np.ndarray, seed: int | tuple[int, ...] = 0, scale_range: tuple[float, float] = (0.05, 20.0)
) -> RelativeInverse:
    """``scale / depth + shift`` with a log-uniform ``scale`` in ``scale_range`` and a
    uniform ``shift`` in ``[0, 2 x median(scale / depth)]``: what a disparity network
    (MiDaS, DPT, Depth Anything) gives, an affine-invariant inverse depth whose scale and
    shift change from image to image. Seeded, so a keyframe always gets the same pair."""
    depth = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise ValueError('simulated relative prior: the depth has no positive pixel')
    rng = np.random.default_rng(seed)
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    scale = float(np.exp(rng.uniform(lo, hi)))
    with np.errstate(divide='ignore', invalid='ignore'):
        inverse = np.where(valid, scale / depth, np.nan)
    shift = float(rng.uniform(0.0, 2.0 * np.nanmedian(inverse)))
    return RelativeInverse((inverse + shift).astype(np.float32), scale, shift)
