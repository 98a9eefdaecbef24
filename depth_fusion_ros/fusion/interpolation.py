"""The weighted interpolation of the fusion (paper eq. (2)): exact (chunked) and fast modes.

With ``v_q = m_q - s_q`` the fused depth is ``f_p = s_p + Σ_q W_pq v_q`` because the
normalised weights sum to one, so this module computes the *offset field* ``f - s``.

* **exact** — every pixel against every point of Ω. Pixels are processed in chunks of
  ``chunk_elements // |Ω|`` so one ``(chunk, |Ω|)`` weight block (float32) bounds memory
  whatever |Ω| is (the default 2**21 pairs is 8 MB per block). Per chunk: the unnormalised
  weights, their per-pixel minimum, ``Σ (W̃ - min)`` and ``Σ (W̃ - min) v`` — the
  min-subtracted normalisation of eq. (9) computed exactly, element by element.
* **fast** — the exact sum on a coarse grid of pixels (every ``fast_stride``-th row and
  column, plus the last ones), then a structure-guided upsampling of the offset field: each
  pixel blends the four coarse pixels around it with bilinear weights times the paper's own
  structure factors (W2·W3·W4 between the pixel and the coarse pixel, squared), so offsets
  do not bleed across depth edges of ``s``. Pixels that no corner represents — no usable
  corner (holes of ``s``), or every corner's structure factor below ``fast_refine`` (the
  pixels on depth edges of ``s``, thin structures between coarse pixels) — are computed
  exactly. The cost falls by about ``fast_stride²``; the error against exact is measured by
  the ``fused_fast`` evaluation method and the benchmark.

``compile_kernel`` runs the per-chunk kernel and the corner blend through ``torch.compile``;
the eager path uses an in-place two-pass kernel. The compiled kernel makes ONE pass over Ω
per pixel (``ΣW̃v``, ``ΣW̃``, ``ΣW̃d``, ``min W̃`` and ``Σd`` in one loop, the min subtracted
afterwards, which is exact algebra) with a polynomial exp as accurate as float32's own: it is
bound by the three exponentials per weight, and nothing of size (pixels, Ω) touches memory.

With ``certainty_floor`` > 0 every offset is also multiplied by ``ΣW̃ / (ΣW̃ + κ)``
(:func:`certainty_share`), in the exact sums, so the fast mode blends faded offsets.

Besides the offset, both modes return the support distance ``Σ_q W_pq ‖p - q‖`` per pixel,
from which :func:`confidence_from_support` derives the confidence.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..chunking import effective_chunk_elements
from ..compile_lock import COMPILE_LOCK, compile_serialised
from .weights import (
    MAX_EXPONENT,
    Samples,
    WeightParams,
    depth_gradients,
    samples_at,
    structure_weights,
    unnormalised_weights,
)

log = logging.getLogger(__name__)

#: Fast mode: corners are blended with bilinear x structure**CORNER_SHARPNESS, so a corner of a
#: different structure (the other side of a depth edge) hardly counts.
CORNER_SHARPNESS = 2.0
MODES = ('exact', 'fast')

#: Smallest point log weight: a point weighs at least exp(-20) = 2e-9 of the paper's weight,
#: so its exponent stays far inside MAX_EXPONENT's range.
MAX_POINT_LOG_WEIGHT = 20.0

#: Largest κ (in units of one point's largest weight) a keyframe's evidence may raise the floor
#: to (``FusionConfig.certainty_gain``): a correction then needs the weight of ten close
#: points to be half kept.
MAX_CERTAINTY_FLOOR = 10.0

#: Default pixel-point pairs per chunk: 8 MB per float32 weight block.
DEFAULT_CHUNK_ELEMENTS = 1 << 21

#: Rows whose min-subtracted weights sum to at most this fraction of the plain sum (times
#: |Ω|) have "all weights equal" up to float32 rounding and use plain normalisation.
EQUAL_WEIGHTS_RTOL = float(np.finfo(np.float32).eps)


@dataclass
class Interpolation:
    """Offset field ``f - s`` (float32, NaN where ``s`` is NaN or Ω is empty) and the support
    distance ``D_p = Σ_q W_pq ‖p - q‖`` (pixels, float32, NaN there) on the working grid."""

    offset: np.ndarray
    support_distance: np.ndarray
    #: Mean share of the correction the certainty floor kept (:func:`certainty_share`) over
    #: the pixels computed exactly (the coarse grid in the fast mode); 1 without a floor.
    kept: float = 1.0


def confidence_from_support(support_distance: np.ndarray, sigma1: float) -> np.ndarray:
    """Per-pixel confidence in [0, 1]: ``exp(-D_p / σ1)``, 0 where there is no estimate.

    ``D_p`` is the distance to Ω averaged with the pixel's own normalised fusion weights, so
    it grows both when the points are far and when the near points have another structure
    (W2..W4 then move the weight to farther points): 1 on a point of Ω, 0.37 when the
    support is σ1 pixels away on average. The published confidence is this times the points'
    agreement (:mod:`.agreement`): nearness alone put the pixels on the points, which carry
    each point's own error, at the top.
    """
    d = np.asarray(support_distance, dtype=np.float64)
    with np.errstate(invalid='ignore'):
        conf = np.exp(-np.maximum(d, 0.0) / sigma1)
    return np.nan_to_num(conf, nan=0.0).astype(np.float32)


def _chunk_sums_inplace(
    p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None, params: WeightParams
) -> tuple[torch.Tensor, ...]:
    """Pixels ``p`` (C, 1) against points ``q`` (1, Q), with ``W' = W̃ - min W̃`` and
    ``d = ‖p - q‖``: ``(ΣW'v, ΣW', ΣW'd, min W̃)`` per pixel, in place on two (C, Q) buffers.

    The formulas of :mod:`.weights` (a test compares them), streamed through memory as few
    times as eager torch allows. ``lw``: the points' log weights (1, Q), or None (all 1).
    """
    dx = q.x - p.x
    dy = q.y - p.y
    distance = torch.hypot(dx, dy)
    w = torch.mul(distance, -1.0 / params.sigma1)
    if lw is not None:
        w.add_(lw)
    w = w.clamp_(min=-MAX_EXPONENT).exp_()
    if params.use_w2:
        t = torch.sub(q.gx, p.gx).abs_().add_(params.sigma2)
        w.div_(t.mul_(torch.sub(q.gy, p.gy).abs_().add_(params.sigma2)))
    if params.use_w34:
        offset = p.s - q.s
        for grad, delta in ((p.gx, dx), (p.gy, dy)):
            torch.addcmul(offset, grad, delta, out=delta)  # delta is not needed after this
            delta.abs_().clamp_(max=MAX_EXPONENT).neg_().exp_().add_(params.sigma3)
            w.mul_(delta)
    low = w.amin(dim=1, keepdim=True)
    w.sub_(low)
    return w @ v, w.sum(dim=1), w.mul_(distance).sum(dim=1), low.squeeze(1)


#: exp(r) on |r| <= ln(2)/2: degree-4 minimax coefficients of the relative error, c0..c4, c0
#: held at 1 so that exp(0) is exactly 1 (float32 evaluation 2.9e-6 relative; float32's own exp
#: 6e-8). Why not the float32-accurate degree 6 (1e-7): each weight feeds sums over |Ω| points
#: (2000 by default) that float32 accumulates with a rounding error of the same order (about
#: sqrt(|Ω|) ulp, 3e-6), and the exact fusion's offsets move by 2.8e-7 m on the bench scene,
#: while the kernel runs 1.15-1.2x faster on 2 threads (degree 5 is as slow as 6: docs/performance.md).
_EXP_MINIMAX = (
    1.0,
    0.9999668598175049,
    0.5000301599502563,
    0.16787473857402802,
    0.041513845324516296,
)
#: Bound of :func:`_exp_nonpositive`'s relative error (tests hold the kernel to it).
EXP_RTOL = 3e-6
#: ln 2 split so ``k * _LN2_HI`` is exact in float32 for the ``|k| <= 87`` used here (Cody-Waite).
_LN2_HI = 0.693359375
_LN2_LO = -2.12194440e-4


def _exp_nonpositive(x: torch.Tensor) -> torch.Tensor:
    """``exp(x)`` for float32 ``x`` in ``[-MAX_EXPONENT, 0]`` to < 3e-6 relative, in plain
    tensor operations that ``torch.compile`` fuses into the kernel's loop.

    ``exp(x) = 2**k exp(r)``: ``k = round(x / ln 2)`` goes straight into the exponent bits,
    ``r = x - k ln 2`` (two-part ln 2, so ``r`` is accurate to float32 rounding) by a degree-4
    minimax polynomial (Horner: four fused multiply-adds once compiled with FMA). Measured on
    2 threads, this form beat Estrin's scheme and a magic-number rounding with exponent-bit
    addition, which were as fast or faster on one thread (docs/performance.md).
    """
    k = torch.round(x * 1.4426950408889634)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    poly = torch.full_like(r, _EXP_MINIMAX[-1])
    for c in reversed(_EXP_MINIMAX[:-1]):
        poly = poly * r + c
    # k in [-87, 0] here, so 127 + k is a normal exponent field: 2**k exactly.
    scale = ((k.to(torch.int32) + 127) << 23).view(torch.float32)
    return poly * scale


def _at_least(x: torch.Tensor, low: float) -> torch.Tensor:
    """``max(x, low)`` as a compare and a blend (inductor's ``clamp`` keeps NaN: 3 instructions)."""
    return torch.where(x < low, low, x)


def _chunk_sums_one_pass(
    p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None, params: WeightParams
) -> tuple[torch.Tensor, ...]:
    """``(ΣW̃v, ΣW̃, ΣW̃d, min W̃, Σd)`` per pixel in ONE pass over Ω (what torch.compile
    turns into a single loop with five accumulators, nothing of size (C, Q) in memory).

    The min-subtracted sums of :func:`_chunk_sums_inplace` follow exactly: ``Σ(W̃ - m)v = ΣW̃v - mΣv``,
    ``Σ(W̃ - m) = ΣW̃ - |Ω|m``, ``Σ(W̃ - m)d = ΣW̃d - mΣd`` (see :func:`_one_pass_kernel`, which
    sends rows where ``|Ω|m`` is not negligible next to ``ΣW̃`` to the two-pass kernel).
    Same factors as :func:`.weights.unnormalised_weights`, with :func:`_exp_nonpositive` for
    the exponentials. The order of the expressions is the order of the generated loop body:
    the longest chain (distance, its square root, W1's exponential) comes first so that the
    CPU overlaps the others with it.
    """
    dx = q.x - p.x
    dy = q.y - p.y
    distance = torch.sqrt(dx * dx + dy * dy)
    distance_sum = distance.sum(dim=1)
    exponent = distance * (-1.0 / params.sigma1)
    if lw is not None:  # the point's own weight folded into W1's exponential: one add
        exponent = exponent + lw
    w = _exp_nonpositive(_at_least(exponent, -MAX_EXPONENT))
    if params.use_w34:
        offset = p.s - q.s
        w3 = _exp_nonpositive(_at_least(-torch.abs(offset + p.gx * dx), -MAX_EXPONENT)) + params.sigma3
        w4 = _exp_nonpositive(_at_least(-torch.abs(offset + p.gy * dy), -MAX_EXPONENT)) + params.sigma3
        structure = w3 * w4
    if params.use_w2:
        w2 = 1.0 / ((torch.abs(q.gx - p.gx) + params.sigma2) * (torch.abs(q.gy - p.gy) + params.sigma2))
        structure = structure * w2 if params.use_w34 else w2
    if params.use_w2 or params.use_w34:
        w = w * structure
    weighted_distance = (w * distance).sum(dim=1)
    return (w * v).sum(dim=1), w.sum(dim=1), weighted_distance, w.amin(dim=1), distance_sum


#: One-pass rows whose min-subtraction ``|Ω| min W̃`` exceeds this fraction of ``ΣW̃`` are
#: recomputed with the two-pass kernel. Below it ``ΣW̃ - |Ω| min`` loses at most a factor
#: 1 / (1 - 0.1) of float32 precision (the numerator and the distance sum at most a factor 2,
#: since ``min Σ|v| <= ΣW̃|v|``); above it, up to all weights equal (|Ω| = 1, where the
#: plain-normalisation guard takes over), the subtraction would cancel digits.
ONE_PASS_MIN_RTOL = 0.1
#: Fewest pixels per kernel call: a single fix-up pixel is padded to two. The kernels are
#: compiled for dynamic sizes, which torch.compile makes from 2 up: one pixel is a size it
#: specialises for, so the first keyframe whose fast mode fixed up a single pixel recompiled
#: the kernel mid-stream (seconds on the fusion node's thread: the live keyframes behind it
#: were dropped, docs/performance.md "GPU"); the ahead-of-time package does not take it at all
#: (two passes instead).
MIN_KERNEL_ROWS = 2
#: Pixels per call of the one-pass kernel: it holds nothing of size (pixels, Ω), so the
#: chunks are only as small as keeps every thread busy and the per-call overhead negligible.
ONE_PASS_ROWS = 8192


def _one_pass_kernel(
    sums: Callable, params: WeightParams, chunk_elements: int, n_points: int = 1
) -> Callable:
    """The ``(ΣW'v, ΣW', ΣW'd, min W̃)`` kernel of :func:`_offsets_at` from the one-pass sums
    ``sums(p, q, v, lw)`` (compiled), its shaky rows redone by :func:`_chunk_sums_inplace` in
    blocks of ``chunk_elements`` pairs. ``kernel.rows`` tells :func:`_offsets_at` its chunk:
    ``ONE_PASS_ROWS``, or ``chunk_elements / n_points`` (|Ω|) where that is more."""

    def kernel(p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        n_q = q.x.shape[-1]
        block = max(1, chunk_elements // max(1, n_q))
        one_pass = sums(p, q, v, lw)
        if one_pass is None:  # the compiler failed: two passes, in blocks of bounded memory
            parts = [
                _chunk_sums_inplace(p.take(slice(i, i + block)), q, v, lw, params)
                for i in range(0, len(p.x), block)
            ]
            return tuple(torch.cat(column) for column in zip(*parts, strict=True))
        wv, w, wd, low, d = one_pass
        num = wv - low * v.sum()
        den = w - n_q * low
        dist = wd - low * d
        shaky = torch.nonzero(n_q * low > ONE_PASS_MIN_RTOL * w).squeeze(1)
        for start in range(0, shaky.numel(), block):
            rows = shaky[start : start + block]
            exact = _chunk_sums_inplace(Samples(*(t[rows] for t in p)), q, v, lw, params)
            for out, value in zip((num, den, dist), exact[:3], strict=True):
                out[rows] = value
        return num, den, dist, low

    # chunk_elements per point already gives more rows than ONE_PASS_ROWS on CUDA (64 M elements).
    kernel.rows = max(ONE_PASS_ROWS, chunk_elements // max(1, n_points))  # type: ignore[attr-defined]
    return kernel


def _no_one_pass(*args: object) -> None:
    """Fallback of the compiled one-pass sums: ``None`` tells :func:`_one_pass_kernel` to use
    the two-pass eager kernel (the one-pass form in eager would hold a dozen (pixels, Ω)
    temporaries)."""
    return None


_COMPILED: dict[tuple, Callable] = {}
_COMPILE_FAILED: set[str] = set()

#: Inductor settings of the fusion kernels. C++ (CPU): contract ``a * b + c`` into fused
#: multiply-adds (inductor's default is ``-ffp-contract=off``; every polynomial step and sum
#: becomes one instruction, rounded once: as accurate or more; 1.3x faster). Both backends:
#: never split the one-pass loop by materialising an intermediate of size (pixels, Ω), which
#: inductor does by default for an expression read more than 4 times (the weight is read
#: by the five sums: three loops and two 64 MB buffers per chunk instead of one loop).
#: C++: the loops' thread count is the caller's at run time (``#pragma omp parallel`` without
#: ``num_threads``; torch's OpenMP runtime, which ``torch.set_num_threads`` sets), not the
#: builder's: without it a build in a one-thread process (a fusion node's background builder,
#: ``OMP_NUM_THREADS=1``) emitted no parallel loop at all, and every process that loaded that
#: library fused on one core (exact 0.167 s at 2 threads against 0.089 s; docs/performance.md).
_INDUCTOR_OPTIONS = {
    'cpp.enable_floating_point_contract_flag': 'fast',
    'realize_reads_threshold': 1 << 20,
    'cpp.dynamic_threads': True,
}

#: On a CPU the kernel is called through inductor's C++ wrapper: the default Python wrapper's
#: binding holds the GIL while the C++ loop runs (40-95 ms a keyframe), so in the composed graph
#: every other node's Python waited for it; the C++ wrapper releases it around the call. Measured
#: (docs/performance.md, 2026-11-27): composed paced median latency 480-510 -> 434-440 ms, the
#: multi-view node's mean 217-222 -> 121-138 ms; the same offsets bit for bit; the compile about
#: as long (``warm_up`` with an empty cache 15.5 against 14.6 s on 2 cores, a warm one 4.8 / 4.7 s).
_CPU_INDUCTOR_OPTIONS = {'cpp_wrapper': True}


def _inductor_options(device: torch.device) -> dict[str, object]:
    """The :data:`_INDUCTOR_OPTIONS` (and on a CPU :data:`_CPU_INDUCTOR_OPTIONS`) this torch
    knows (names move between releases; an unknown one would make ``torch.compile`` raise).
    Imports the compiler, so holding ``COMPILE_LOCK`` (compile_lock.py)."""
    try:
        with COMPILE_LOCK:
            import torch._inductor.config as inductor_config

            known = inductor_config.get_config_copy()
    except Exception:  # no inductor at all: compiling fails later (logged) and falls back to eager
        return {}
    options = dict(_INDUCTOR_OPTIONS)
    if device.type == 'cpu':
        options.update(_CPU_INDUCTOR_OPTIONS)
    return {name: value for name, value in options.items() if name in known}


def _maybe_compiled(
    name: str,
    fn: Callable,
    params: WeightParams,
    compile_kernel: bool,
    device: torch.device,
    fallback: Callable | None = None,
) -> Callable:
    """``fn(*args, params)`` as a function of ``args``, compiled with ``torch.compile``
    (inductor) when asked and possible.

    Compiling fuses the elementwise passes into one loop (several times faster on CPU than
    eager). A failing compiler (no C++ toolchain, unsupported platform) is logged once and
    eager code is used from then on: same numbers, only slower. ``fallback(*args)`` replaces
    the eager ``fn`` after a failure when given (a kernel whose eager form would not bound
    its memory).
    """

    def eager(*args: object) -> tuple[torch.Tensor, ...]:
        return fn(*args, params)

    if not compile_kernel or device.type in _COMPILE_FAILED:
        return eager
    from . import aot_kernels  # a package built ahead of time (depth-fusion kernels) needs no compile

    compiled = aot_kernels.kernel(name, params, device)
    what = (
        'the ahead-of-time fusion kernels' if compiled is not None else 'torch.compile of the fusion kernels'
    )
    if compiled is None:
        key = (name, params, device.type)
        if key not in _COMPILED:
            # Serialised: a compile session flips a process-wide flag other threads read, and the
            # compiler's first import must not race another thread's (compile_lock.py).
            _COMPILED[key] = compile_serialised(eager, dynamic=True, options=_inductor_options(device))
        compiled = _COMPILED[key]

    backup = fallback or eager

    def guarded(*args: object) -> tuple[torch.Tensor, ...]:
        if device.type in _COMPILE_FAILED:
            return backup(*args)
        try:
            return compiled(*args)
        except Exception as exc:  # the compiler stack raises many types; any failure means eager
            _COMPILE_FAILED.add(device.type)
            log.warning('%s failed on %s (%s); using eager', what, device, exc)
            return backup(*args)

    return guarded


def _plain_normalisation(
    p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None, params: WeightParams
) -> tuple[torch.Tensor, torch.Tensor]:
    """Offsets and support distances with ``W̃ / Σ W̃`` (the guard of eq. (9)); equal weights
    where even ``Σ W̃`` is 0 (every weight underflowed, only possible with σ3 = 0)."""
    w = unnormalised_weights(p, q, params, lw)
    distance = torch.sqrt((q.x - p.x) ** 2 + (q.y - p.y) ** 2)
    w = torch.where(w.sum(dim=1, keepdim=True) > 0, w, torch.ones_like(w))
    total = w.sum(dim=1)
    return (w @ v) / total, (w * distance).sum(dim=1) / total


def _offsets_at(
    pixels: Samples,
    points: Samples,
    v: torch.Tensor,
    lw: torch.Tensor | None,
    kernel: Callable,
    chunk_elements: int,
    params: WeightParams,
    floor: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact offsets and support distances of ``pixels`` (1-D samples) against Ω, whose log
    weights are ``lw`` (1, |Ω|; None: all points weigh 1), and the mean kept share (0-d).

    ``floor`` (κ, in weight units): every offset times its share ``ΣW̃ / (ΣW̃ + κ)`` (the
    certainty fade, :func:`certainty_share`); 0 leaves the paper's normalised offsets (no
    multiply, a share of 1).

    Chunks have a fixed size (the last one padded by repeating a pixel) so a compiled kernel
    sees one pixel-count shape per |Ω|; the size is balanced (never above the kernel's) so
    the padding is under one pixel per chunk (8192-pixel chunks would pad 76,800 pixels to
    81,920), and at least ``MIN_KERNEL_ROWS``. Rows whose weights are all equal (the
    min-subtracted sum vanishes next to the plain sum ``ΣW' + |Ω|·min``; always when |Ω| = 1)
    are redone with plain normalisation.
    """
    n = pixels.x.numel()
    n_points = points.x.numel()
    block = max(1, chunk_elements // max(1, n_points))  # rows of one (rows, Ω) weight block
    chunk = int(max(1, min(n, getattr(kernel, 'rows', None) or block)))
    chunk = -(-n // -(-n // chunk))  # as many chunks, of equal size: the padding is < one per chunk
    chunk = max(chunk, MIN_KERNEL_ROWS)
    q = points.row()
    offsets = torch.empty(n, dtype=v.dtype, device=v.device)
    support = torch.empty(n, dtype=v.dtype, device=v.device)
    kept = torch.zeros((), dtype=torch.float64, device=v.device)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        index = torch.arange(start, start + chunk, device=v.device).clamp_max(n - 1)
        num, den, dist, low = kernel(pixels.take(index).column(), q, v, lw)
        plain = den + n_points * low
        offsets[start:stop] = (num / den)[: stop - start]
        support[start:stop] = (dist / den)[: stop - start]
        equal = (den <= (EQUAL_WEIGHTS_RTOL * n_points) * plain)[: stop - start]
        # One host round trip (the nonzero), not two (an any() then a masked select).
        equal_rows = torch.nonzero(equal).squeeze(1).add_(start)
        if equal_rows.numel():
            for first in range(0, equal_rows.numel(), block):
                rows = equal_rows[first : first + block]
                off, sup = _plain_normalisation(pixels.take(rows).column(), q, v, lw, params)
                offsets[rows] = off
                support[rows] = sup
        if floor > 0:  # after the plain-normalisation redo, which fades the same way
            share = certainty_share(plain[: stop - start], floor)
            offsets[start:stop] *= share
            kept += share.sum(dtype=torch.float64)
    return offsets, support, kept / n if floor > 0 else torch.ones((), dtype=torch.float64)


def certainty_share(mass: torch.Tensor, floor: float) -> torch.Tensor:
    """``ΣW̃ / (ΣW̃ + κ)``: the share of its normalised correction a pixel keeps.

    The paper's weights are normalised, so a pixel that no point resembles (far from all of
    them, or of another structure under W2-W4) still takes a full weighted average of their
    offsets, though its single-view error has nothing to do with theirs. A pseudo
    observation "no correction" of weight κ at every pixel (normalised convolution with a
    certainty floor) keeps the full correction where the points' total weight dwarfs κ and
    fades it to none where it is far below (docs/fusion.md "Certainty floor"). ``floor`` 0:
    all ones (the paper).
    """
    return mass / (mass + floor) if floor > 0 else torch.ones_like(mass)


def interpolate(
    s: np.ndarray,
    m: np.ndarray,
    omega: np.ndarray,
    params: WeightParams | None = None,
    *,
    mode: str = 'exact',
    fast_stride: int = 4,
    fast_refine: float = 0.3,
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
    device: str | torch.device = 'cpu',
    compile_kernel: bool = False,
    point_weight: np.ndarray | None = None,
    certainty_floor: float = 0.0,
) -> Interpolation:
    """Offset field ``f - s`` of the fusion of ``s`` with the points ``omega`` of ``m``.

    ``s``: single-view depth in metres (HxW, NaN = none); ``m``: multi-view depth (HxW);
    ``omega``: bool HxW mask of the selected points (points where ``s`` or ``m`` is not
    finite are ignored). ``point_weight``: optional HxW factor in (0, 1] that multiplies
    every weight of a point of Ω (its precision, :func:`precision_weights`; NaN = 1); None
    gives the paper's weights. ``certainty_floor``: κ as a fraction of one point's largest
    weight (:attr:`WeightParams.max_weight`); every offset is faded by ``ΣW̃ / (ΣW̃ + κ)``
    (:func:`certainty_share`; 0: the paper). Returns NaN offsets everywhere when Ω is empty
    — the caller decides the fallback.
    """
    params = params or WeightParams()
    s = np.asarray(s, dtype=np.float32)
    m = np.asarray(m, dtype=np.float32)
    omega = np.asarray(omega, dtype=bool)
    if s.ndim != 2 or s.shape != m.shape or s.shape != omega.shape:
        raise ValueError(
            f'single-view {s.shape}, multi-view {m.shape} and omega {omega.shape} must be HxW of one size'
        )
    if mode not in MODES:
        raise ValueError(f'mode must be one of {", ".join(MODES)}, got {mode!r}')
    if chunk_elements < 1:
        raise ValueError(f'chunk_elements must be >= 1, got {chunk_elements}')
    if fast_stride < 1:
        raise ValueError(f'fast_stride must be >= 1, got {fast_stride}')
    if not 0.0 <= fast_refine <= 1.0:
        raise ValueError(f'fast_refine must be in [0, 1], got {fast_refine}')
    check_certainty_floor(certainty_floor, MAX_CERTAINTY_FLOOR)
    unit = np.float32(params.structure_scale)
    if unit != 1.0:
        # The weights' structure factors compare depths and depth gradients in metres (the
        # paper's W2-W4 as written); in units of ``structure_scale`` they are that much
        # sharper. W1 does not see depth, and the offsets are linear in it, so the scaled
        # interpolation is the same kernel on ``s / unit`` and ``m / unit``, its offset
        # times ``unit``. The fast mode's ``fast_refine`` is a threshold on those factors at
        # the paper's scale; sharpened, W3·W4 is its own ``1 / unit``-th power, so the
        # threshold follows it and the fast mode computes about the same pixels exactly (at
        # 0.3 m with 0.3 unchanged it computed twice the time's worth, for the same depth).
        scaled = interpolate(
            s / unit,
            m / unit,
            omega,
            dataclasses.replace(params, structure_scale=1.0),
            mode=mode,
            fast_stride=fast_stride,
            fast_refine=float(fast_refine) ** (1.0 / float(unit)),
            chunk_elements=chunk_elements,
            device=device,
            compile_kernel=compile_kernel,
            point_weight=point_weight,
            certainty_floor=certainty_floor,
        )
        return Interpolation((scaled.offset * unit).astype(np.float32), scaled.support_distance, scaled.kept)
    width = s.shape[1]
    valid_s = np.isfinite(s)
    points_mask = omega & valid_s & np.isfinite(m)
    offset = np.full(s.shape, np.nan, dtype=np.float32)
    support = np.full(s.shape, np.nan, dtype=np.float32)
    if not points_mask.any() or not valid_s.any():
        return Interpolation(offset, support)

    dev = torch.device(device)
    chunk_elements = effective_chunk_elements(chunk_elements, dev)
    gx_np, gy_np = depth_gradients(s)
    s_t = torch.from_numpy(np.where(valid_s, s, 0.0).astype(np.float32).ravel()).to(dev)
    gx = torch.from_numpy(gx_np.ravel()).to(dev)
    gy = torch.from_numpy(gy_np.ravel()).to(dev)
    point_index = torch.from_numpy(np.flatnonzero(points_mask)).to(dev)
    points = samples_at(point_index, width, s_t, gx, gy)
    v = torch.from_numpy((m - s)[points_mask].astype(np.float32)).to(dev)
    lw = _point_log_weights(point_weight, points_mask, dev)
    floor = float(certainty_floor) * params.max_weight
    # Eager: the in-place two-pass kernel (fewer passes over memory); compiled: the one-pass
    # sums fused into one loop over Ω.
    if compile_kernel and dev.type not in _COMPILE_FAILED:
        kernel = _one_pass_kernel(
            _maybe_compiled('sums', _chunk_sums_one_pass, params, True, dev, fallback=_no_one_pass),
            params,
            chunk_elements,
            int(points.x.numel()),
        )
    else:
        kernel = functools.partial(_chunk_sums_inplace, params=params)

    if mode == 'exact' or fast_stride == 1:
        pixel_index = torch.from_numpy(np.flatnonzero(valid_s)).to(dev)
        off, sup, kept = _offsets_at(
            samples_at(pixel_index, width, s_t, gx, gy), points, v, lw, kernel, chunk_elements, params, floor
        )
        offset.ravel()[valid_s.ravel()] = off.cpu().numpy()
        support.ravel()[valid_s.ravel()] = sup.cpu().numpy()
        return Interpolation(offset, support, float(kept))

    off_t, support_t, kept = _fast_offsets(
        valid_s,
        s_t,
        gx,
        gy,
        points,
        v,
        lw,
        params,
        kernel,
        chunk_elements,
        fast_stride,
        fast_refine,
        _maybe_compiled('blend', _blend_corners, params, compile_kernel, dev),
        floor,
    )
    offset.ravel()[:] = off_t.cpu().numpy()
    support.ravel()[:] = support_t.cpu().numpy()
    offset[~valid_s] = np.nan
    support[~valid_s] = np.nan
    return Interpolation(offset, support, float(kept))


def _point_log_weights(
    point_weight: np.ndarray | None, points_mask: np.ndarray, device: torch.device
) -> torch.Tensor | None:
    """``log point_weight`` of the points of Ω as a (1, |Ω|) row (NaN: weight 1), or None.

    A log weight joins W1's exponent (``exp(-d/σ1 + log c) = c·W1``), so the kernels weigh
    a point by its precision for one addition per pixel-point pair.
    """
    if point_weight is None:
        return None
    c = np.asarray(point_weight, dtype=np.float32)
    if c.shape != points_mask.shape:
        raise ValueError(f'point_weight {c.shape} must be HxW like omega {points_mask.shape}')
    c = c[points_mask]
    c = np.where(np.isfinite(c), c, 1.0)
    if (c <= 0).any() or (c > 1).any():
        raise ValueError('point_weight must be in (0, 1] on the points of omega')
    lw = np.maximum(np.log(c), -MAX_POINT_LOG_WEIGHT).astype(np.float32)
    return torch.from_numpy(lw).to(device).reshape(1, -1)


def check_certainty_floor(value: float, upper: float = 1.0) -> None:
    """``certainty_floor`` is a finite fraction in [0, ``upper``] of one point's largest weight
    (the configured floor: 1; the one a keyframe's evidence raised it to: ``MAX_CERTAINTY_FLOOR``)."""
    if not (np.isfinite(value) and 0.0 <= value <= upper):
        raise ValueError(f'certainty_floor must be in [0, {upper:g}] (0: off), got {value}')


def coarse_axis(size: int, stride: int) -> np.ndarray:
    """Coarse sample positions along one axis: every ``stride``-th pixel and the last one."""
    axis = np.arange(0, size, stride)
    return axis if axis[-1] == size - 1 else np.append(axis, size - 1)


@dataclass(frozen=True)
class _CoarseGrid:
    """Geometry of the fast mode for one image size and stride (cached: it never changes).

    ``coarse_flat``: flat pixel index of each coarse sample; per pixel (rows of ``H*W``):
    ``corner_index`` (4 coarse samples around it, into ``coarse_flat``), ``corner_flat``
    (their flat pixel indices), ``bilinear`` weights, and the corner-minus-pixel offsets
    ``dx``/``dy`` in pixels.
    """

    coarse_flat: np.ndarray
    corner_index: torch.Tensor
    corner_flat: torch.Tensor
    bilinear: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor


@functools.lru_cache(maxsize=8)
def _coarse_grid(height: int, width: int, stride: int, device: torch.device) -> _CoarseGrid:
    xs = coarse_axis(width, stride)
    ys = coarse_axis(height, stride)
    coarse_flat = (ys[:, None] * width + xs[None, :]).ravel()
    cell_x = np.clip(np.searchsorted(xs, np.arange(width), side='right') - 1, 0, len(xs) - 2)
    cell_y = np.clip(np.searchsorted(ys, np.arange(height), side='right') - 1, 0, len(ys) - 2)
    fx = (np.arange(width) - xs[cell_x]) / (xs[cell_x + 1] - xs[cell_x])
    fy = (np.arange(height) - ys[cell_y]) / (ys[cell_y + 1] - ys[cell_y])
    corners, bilinear, dxs, dys = [], [], [], []
    for oy, wy in ((0, 1.0 - fy), (1, fy)):
        for ox, wx in ((0, 1.0 - fx), (1, fx)):
            corners.append(((cell_y + oy)[:, None] * len(xs) + (cell_x + ox)[None, :]).ravel())
            bilinear.append((wy[:, None] * wx[None, :]).ravel())
            dxs.append(
                np.broadcast_to((xs[cell_x + ox] - np.arange(width))[None, :], (height, width)).ravel()
            )
            dys.append(
                np.broadcast_to((ys[cell_y + oy] - np.arange(height))[:, None], (height, width)).ravel()
            )
    corner_index = np.stack(corners, axis=1)

    def tensor(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(device=device, dtype=dtype)

    return _CoarseGrid(
        coarse_flat=coarse_flat,
        corner_index=tensor(corner_index, torch.int64),
        corner_flat=tensor(coarse_flat[corner_index], torch.int64),
        bilinear=tensor(np.stack(bilinear, axis=1), torch.float32),
        dx=tensor(np.stack(dxs, axis=1), torch.float32),
        dy=tensor(np.stack(dys, axis=1), torch.float32),
    )


def _blend_corners(
    pixels: Samples,
    corners: Samples,
    dx: torch.Tensor,
    dy: torch.Tensor,
    bilinear: torch.Tensor,
    corner_offset: torch.Tensor,
    corner_support: torch.Tensor,
    params: WeightParams,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Structure-guided bilinear blend of the four corners of every pixel.

    ``pixels`` are (N, 1), ``corners`` and the rest (N, 4). Returns the blended offset and
    support distance, the total blend weight and the best corner structure factor.
    """
    structure = structure_weights(pixels, corners, params, dx, dy) * (1.0 / params.max_weight)
    usable = torch.isfinite(corner_offset) & (bilinear > 0)
    blend = torch.where(usable, bilinear * structure.pow(CORNER_SHARPNESS), torch.zeros_like(bilinear))
    total = blend.sum(dim=1)
    norm = 1.0 / total.clamp_min(torch.finfo(bilinear.dtype).tiny)
    offset = (blend * torch.where(usable, corner_offset, torch.zeros_like(bilinear))).sum(dim=1) * norm
    support = (blend * torch.where(usable, corner_support, torch.zeros_like(bilinear))).sum(dim=1) * norm
    best = torch.where(usable, structure, torch.zeros_like(structure)).amax(dim=1)
    return offset, support, total, best


def _fast_offsets(
    valid_s: np.ndarray,
    s: torch.Tensor,
    gx: torch.Tensor,
    gy: torch.Tensor,
    points: Samples,
    v: torch.Tensor,
    lw: torch.Tensor | None,
    params: WeightParams,
    kernel: Callable,
    chunk_elements: int,
    stride: int,
    refine_below: float,
    blend: Callable,
    floor: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact offsets on a coarse grid, structure-guided bilinear upsampling, exact fix-ups;
    the mean kept share is the coarse grid's (a uniform sample of the image).

    With a certainty ``floor`` the coarse offsets are already faded, so the blend carries
    the fade with them (the blend of faded offsets, not the fade of blended masses: the
    two differ only where the corners' masses differ, and the corners are 4 px apart)."""
    height, width = valid_s.shape
    dev = s.device
    grid = _coarse_grid(height, width, stride, dev)
    coarse_valid = valid_s.ravel()[grid.coarse_flat]
    coarse_offset = torch.full((grid.coarse_flat.size,), float('nan'), dtype=s.dtype, device=dev)
    coarse_support = torch.full((grid.coarse_flat.size,), float('nan'), dtype=s.dtype, device=dev)
    kept = torch.ones((), dtype=torch.float64)  # a 0-d tensor: read once, with the output
    if coarse_valid.any():
        idx = torch.from_numpy(grid.coarse_flat[coarse_valid]).to(dev)
        pixels = samples_at(idx, width, s, gx, gy)
        off, sup, kept = _offsets_at(pixels, points, v, lw, kernel, chunk_elements, params, floor)
        sel = torch.from_numpy(np.flatnonzero(coarse_valid)).to(dev)
        coarse_offset[sel] = off
        coarse_support[sel] = sup

    zero = torch.zeros(1, 1, dtype=s.dtype, device=dev)  # pixel positions enter only through dx, dy
    pixels = Samples(zero, zero, s[:, None], gx[:, None], gy[:, None])
    c = grid.corner_flat
    corners = Samples(zero, zero, s[c], gx[c], gy[c])
    offset, support, total, best = blend(
        pixels,
        corners,
        grid.dx,
        grid.dy,
        grid.bilinear,
        coarse_offset[grid.corner_index],
        coarse_support[grid.corner_index],
    )

    # Pixels the corners cannot represent (no usable corner, or a structure unlike all of
    # them: depth edges of s, thin objects between coarse pixels): compute them exactly.
    fix = ((total <= 0) | (best < refine_below)) & torch.from_numpy(valid_s.ravel()).to(dev)
    # One host round trip (the nonzero): the count for the debug line comes from it, and an
    # any() before it would be a second one.
    idx = torch.nonzero(fix).squeeze(1)
    log.debug('fast fusion: %d of %d pixels computed exactly', idx.numel(), fix.numel())
    if idx.numel():
        pixels = samples_at(idx, width, s, gx, gy)
        off, sup, _ = _offsets_at(pixels, points, v, lw, kernel, chunk_elements, params, floor)
        offset[idx] = off
        support[idx] = sup
    return offset, support, kept
