"""The sums of one chunk of pixels against Ω: the inner kernel of the paper's eq. (2).

For pixels ``p`` and the points ``q`` of Ω, with ``W̃`` the unnormalised weights of
:mod:`.weights`, ``v`` the points' corrections and ``d = ‖p - q‖``, every mode of
:mod:`.interpolation` needs per pixel ``(Σ(W̃ - min)v, Σ(W̃ - min), Σ(W̃ - min)d, min W̃)``: the
min-subtracted normalisation of eq. (9), element by element. Two forms give the same numbers:

* :func:`chunk_sums_inplace`, eager torch: two passes over a (pixels, Ω) block in place, so
  the caller bounds memory by its chunk size;
* :func:`chunk_sums_one_pass`, for ``torch.compile`` / AOTInductor: ONE pass over Ω per pixel
  (``ΣW̃v``, ``ΣW̃``, ``ΣW̃d``, ``min W̃`` and ``Σd`` in one loop, the min subtracted afterwards,
  which is exact algebra) with a polynomial exp as accurate as the sums' own float32 rounding:
  bound by the three exponentials per weight, and nothing of size (pixels, Ω) in memory.
  :func:`one_pass_kernel` subtracts the min and sends the rows where that would cancel digits
  back to the two-pass form.

The ahead-of-time kernels (:mod:`.aot_kernels`) are built from this file's source.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .weights import MAX_EXPONENT, Samples, WeightParams


def chunk_sums_inplace(
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
#: Bound of :func:`exp_nonpositive`'s relative error (tests hold the kernel to it).
EXP_RTOL = 3e-6
#: ln 2 split so ``k * _LN2_HI`` is exact in float32 for the ``|k| <= 87`` used here (Cody-Waite).
_LN2_HI = 0.693359375
_LN2_LO = -2.12194440e-4


def exp_nonpositive(x: torch.Tensor) -> torch.Tensor:
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


def chunk_sums_one_pass(
    p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None, params: WeightParams
) -> tuple[torch.Tensor, ...]:
    """``(ΣW̃v, ΣW̃, ΣW̃d, min W̃, Σd)`` per pixel in ONE pass over Ω (what torch.compile
    turns into a single loop with five accumulators, nothing of size (C, Q) in memory).

    The min-subtracted sums of :func:`chunk_sums_inplace` follow exactly: ``Σ(W̃ - m)v = ΣW̃v - mΣv``,
    ``Σ(W̃ - m) = ΣW̃ - |Ω|m``, ``Σ(W̃ - m)d = ΣW̃d - mΣd`` (see :func:`one_pass_kernel`, which
    sends rows where ``|Ω|m`` is not negligible next to ``ΣW̃`` to the two-pass kernel).
    Same factors as :func:`.weights.unnormalised_weights`, with :func:`exp_nonpositive` for
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
    w = exp_nonpositive(_at_least(exponent, -MAX_EXPONENT))
    if params.use_w34:
        offset = p.s - q.s
        w3 = exp_nonpositive(_at_least(-torch.abs(offset + p.gx * dx), -MAX_EXPONENT)) + params.sigma3
        w4 = exp_nonpositive(_at_least(-torch.abs(offset + p.gy * dy), -MAX_EXPONENT)) + params.sigma3
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
#: Pixels per call of the one-pass kernel: it holds nothing of size (pixels, Ω), so the
#: chunks are only as small as keeps every thread busy and the per-call overhead negligible.
ONE_PASS_ROWS = 8192


def one_pass_kernel(sums: Callable, params: WeightParams, chunk_elements: int, n_points: int = 1) -> Callable:
    """The ``(ΣW'v, ΣW', ΣW'd, min W̃)`` kernel of :func:`.interpolation._offsets_at` from the one-pass sums
    ``sums(p, q, v, lw)`` (compiled), its shaky rows redone by :func:`chunk_sums_inplace` in
    blocks of ``chunk_elements`` pairs. ``kernel.rows`` tells :func:`.interpolation._offsets_at` its chunk:
    ``ONE_PASS_ROWS``, or ``chunk_elements / n_points`` (|Ω|) where that is more."""

    def kernel(p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        n_q = q.x.shape[-1]
        block = max(1, chunk_elements // max(1, n_q))
        one_pass = sums(p, q, v, lw)
        if one_pass is None:  # the compiler failed: two passes, in blocks of bounded memory
            parts = [
                chunk_sums_inplace(p.take(slice(i, i + block)), q, v, lw, params)
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
            exact = chunk_sums_inplace(Samples(*(t[rows] for t in p)), q, v, lw, params)
            for out, value in zip((num, den, dist), exact[:3], strict=True):
                out[rows] = value
        return num, den, dist, low

    # chunk_elements per point already gives more rows than ONE_PASS_ROWS on CUDA (64 M elements).
    kernel.rows = max(ONE_PASS_ROWS, chunk_elements // max(1, n_points))  # type: ignore[attr-defined]
    return kernel


def no_one_pass(*args: object) -> None:
    """Fallback of the compiled one-pass sums: ``None`` tells :func:`one_pass_kernel` to use
    the two-pass eager kernel (the one-pass form in eager would hold a dozen (pixels, Ω)
    temporaries)."""
    return None
