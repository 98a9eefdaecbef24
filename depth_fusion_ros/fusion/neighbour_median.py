"""The median value of each pixel point's nearest neighbours: the guard's local test.

The guard (``guard.py``) compares every Ω point's log residual with the median of its nearest
``max_neighbours`` Ω neighbours within ``radius`` pixels. Ω's points are distinct pixels, so
distances repeat (a ring of up to 16 pixels shares one), and which of several equidistant
neighbours count must be defined, or the median depends on the search's internals. Here they
count in the order of :func:`ring_offsets`, by row then column offset: for Ω's row-major
points, their index order (the per-point reference loop in test/test_fusion_guard.py).

Two searches give those same numbers, one per kind of device, because each is slow on the
other (docs/performance.md "GPU", 2026-12-04):

* on the CPU, SciPy's k-d tree: the ``max_neighbours`` nearest, then the ring at the last one's
  distance read from an index image, so that its members count in ring order (the tree's own
  choice among them is arbitrary). On one thread, as in the fusion node: 9-10 ms at 4096
  points and 21-22 ms at 8192, of which the ring order 1-3 ms; the grid below takes 20-30 ms
  at 4096 there.
* on a GPU, the grid: every offset within the radius, nearest first, read from an index image
  in one gather, the first ``max_neighbours`` occupied ones taken, and the support (every
  neighbour within the radius) counted from the same gather. A few kernels and no host
  synchronisation: 1.8 ms of an H200's host, where the tree took 16.4 ms.
"""

from __future__ import annotations

import ctypes
import functools
import math
from pathlib import Path

import numpy as np
import torch

from ..native_build import kernel_threads, load_native
from ..torch_device import resolve_device


@functools.lru_cache(maxsize=8)
def ring_offsets(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """``(dx, dy)`` of every pixel offset within ``radius`` (inclusive), the centre excluded,
    nearest first; equidistant ones by ``dy``, then ``dx``."""
    r = int(np.floor(radius))
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    d2 = dx * dx + dy * dy
    keep = (d2 > 0) & (d2 <= radius * radius)
    dx, dy, d2 = dx[keep], dy[keep], d2[keep]
    order = np.lexsort((dx, dy, d2))
    return dx[order], dy[order]


def nearest_median(
    cols: np.ndarray,
    rows: np.ndarray,
    values: np.ndarray,
    radius: float,
    max_neighbours: int,
    device: str | torch.device = 'cpu',
    support_step: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: the median of ``values`` over its nearest ``max_neighbours`` other points
    within ``radius`` (NaN without any) and how many neighbours that median is over; and for
    every ``support_step``-th point, how many other points lie within ``radius`` in all.

    ``cols``, ``rows``: distinct non-negative pixel positions (int); ``values``: one float per
    point. The median is ``np.median``'s (the mean of the two middle values for an even count).
    """
    if len(cols) == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    dev = resolve_device(device)
    if dev.type == 'cpu':
        found = native_median(cols, rows, values, radius, max_neighbours)
        if found is None:
            found = tree_median(cols, rows, values, radius, max_neighbours)
        median, count = found
        points = np.stack((cols, rows), axis=1)
        return median, count, grid_counts(points, points[::support_step], radius) - 1
    return grid_median(cols, rows, values, radius, max_neighbours, dev, support_step)


def _median_of_rows(candidates: np.ndarray, count: np.ndarray) -> np.ndarray:
    """``np.median`` of each row's ``count`` finite values (the rest +inf), NaN where none."""
    ordered = np.sort(candidates, axis=1)
    low = np.maximum(count - 1, 0) // 2
    high = np.minimum(count // 2, ordered.shape[1] - 1)
    at = np.arange(len(count))
    return np.where(count > 0, (ordered[at, low] + ordered[at, high]) / 2.0, np.nan)


def _index_image(cols: np.ndarray, rows: np.ndarray, border: int) -> np.ndarray:
    """Point index per pixel of the image bordered by ``border`` pixels (-1: no point)."""
    image = np.full((int(rows.max()) + 1 + 2 * border, int(cols.max()) + 1 + 2 * border), -1, dtype=np.int32)
    image[rows + border, cols + border] = np.arange(len(cols), dtype=np.int32)
    return image


@functools.lru_cache(maxsize=8)
def _rings(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Per squared distance ``s`` (rows 0 .. r²): its offsets ``dx``, ``dy`` in ring order,
    padded with (0, 0) (the centre, never a neighbour) to the largest ring."""
    dx, dy = ring_offsets(radius)
    d2 = dx * dx + dy * dy
    size = np.bincount(d2, minlength=int(np.floor(radius)) ** 2 + 1)
    ring_dx = np.zeros((len(size), max(int(size.max()), 1)), dtype=np.int64)
    ring_dy = np.zeros_like(ring_dx)
    start = np.concatenate(([0], np.cumsum(size)[:-1]))
    slot = np.arange(len(d2)) - start[d2]  # d2 is ascending: each ring's members in order
    ring_dx[d2, slot], ring_dy[d2, slot] = dx, dy
    return ring_dx, ring_dy


#: Points below which the ring walk does not go to the threads (the hand-over costs more).
THREAD_MIN_POINTS = 2048


def native_median(
    cols: np.ndarray, rows: np.ndarray, values: np.ndarray, radius: float, max_neighbours: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`nearest_median`'s median and count on the CPU by ``ring_median.c`` (the ring
    walked point by point in an index image, stopped at the k-th neighbour: 1-3 ms where the
    tree takes 20), or None where the kernel cannot run here (``native_build.load_native``),
    for more than 256 neighbours or a non-finite value (the tree then)."""
    lib = _ring_median_library()
    values = np.ascontiguousarray(values, dtype=np.float64)
    k = int(max_neighbours)
    if lib is None or not 0 < k <= 256 or not np.isfinite(values).all():
        return None
    cols, rows = np.asarray(cols, dtype=np.int64), np.asarray(rows, dtype=np.int64)
    r = int(np.floor(radius))
    image = _index_image(cols, rows, r)
    width = image.shape[1]
    at = np.ascontiguousarray((rows + r) * width + cols + r, dtype=np.int64)
    dx, dy = ring_offsets(radius)
    steps = np.ascontiguousarray(dy * width + dx, dtype=np.int64)
    n = len(cols)
    median = np.empty(n, dtype=np.float64)
    count = np.empty(n, dtype=np.int64)
    threads = kernel_threads(n, THREAD_MIN_POINTS)
    lib.ring_median(
        image.ctypes.data, at.ctypes.data, n, steps.ctypes.data, len(steps),
        values.ctypes.data, k, median.ctypes.data, count.ctypes.data, threads,
    )  # fmt: skip
    return median, count


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now, so that a fusion node's first
    keyframe does not wait for the compiler; whether it will be used."""
    return _ring_median_library() is not None


def _ring_median_library() -> ctypes.CDLL | None:
    p, i64, i = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    signature = {'ring_median': [p, p, i64, p, i64, p, i, p, p, i]}
    return load_native(Path(__file__).with_name('ring_median.c'), signature)


def tree_median(
    cols: np.ndarray, rows: np.ndarray, values: np.ndarray, radius: float, max_neighbours: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`nearest_median` on the CPU: a k-d tree, its ties at the last distance in ring order."""
    from scipy.spatial import cKDTree  # here, not at the top: ~0.3 s off the fusion node's start

    cols, rows = np.asarray(cols, dtype=np.int64), np.asarray(rows, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    n, k = len(cols), int(max_neighbours)
    kq = min(k + 1, n)
    points = np.stack((cols, rows), axis=1).astype(np.float64)
    # query's bound is strict: pixels at exactly the radius count
    distance, index = cKDTree(points).query(
        points, k=kq, distance_upper_bound=radius * (1.0 + 1e-9), workers=_query_workers()
    )
    # Distinct points: each point is its own nearest (column 0), the others follow by distance.
    distance, index = distance.reshape(n, kq)[:, 1:], index.reshape(n, kq)[:, 1:]
    keep = np.isfinite(distance)
    count = keep.sum(axis=1)
    candidates = np.where(keep, values[np.minimum(index, n - 1)], np.inf)
    full = np.flatnonzero(count == k)
    if full.size:
        _ring_order(candidates, full, distance[full], cols, rows, values, radius)
    return _median_of_rows(candidates, count), count


def _ring_order(
    candidates: np.ndarray,
    full: np.ndarray,
    distance: np.ndarray,
    cols: np.ndarray,
    rows: np.ndarray,
    values: np.ndarray,
    radius: float,
) -> None:
    """Rows ``full`` of ``candidates`` (the tree's ``k`` nearest, at ``distance``) with the
    last ring's members in ring order, in place.

    The last neighbour's ring may hold more points than the tree returned, and which of them
    it returned is its own choice. The nearer ones stay (the first columns: the tree's order is
    by distance); where the ring holds more points than the tree took, the ring's columns are
    filled from the ring in ring order. Pixel offsets give bit-identical distances within a
    ring (sums of squared integers), so a ring's members compare equal."""
    k = candidates.shape[1]
    last_d = distance[:, -1]
    n_at = (distance == last_d[:, None]).sum(axis=1)
    last = np.rint(last_d * last_d).astype(np.int64)
    ring_dx, ring_dy = _rings(radius)
    r = int(np.floor(radius))
    image = _index_image(cols, rows, r)
    width = image.shape[1]
    centre = (rows[full] + r) * width + cols[full] + r
    member = image.ravel()[centre[:, None] + (ring_dy * width + ring_dx)[last]]
    occupied = (member >= 0) & (member != full[:, None])  # the padding (0, 0) is the point itself
    cut = np.flatnonzero(occupied.sum(axis=1) > n_at)
    if cut.size == 0:
        return
    at, occupied, member, n_at = full[cut], occupied[cut], member[cut], n_at[cut]
    rank = np.cumsum(occupied, axis=1)
    take = occupied & (rank <= n_at[:, None])
    # Column k collects what is not taken (written there, never read).
    fixed = np.concatenate((candidates[at], np.full((len(at), 1), np.inf)), axis=1)
    slot = np.where(take, (k - n_at)[:, None] + rank - 1, k)
    np.put_along_axis(fixed, slot, np.where(take, values[np.maximum(member, 0)], np.inf), axis=1)
    candidates[at] = fixed[:, :k]


def grid_median(
    cols: np.ndarray,
    rows: np.ndarray,
    values: np.ndarray,
    radius: float,
    max_neighbours: int,
    device: torch.device,
    support_step: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`nearest_median` on a GPU: every offset within the radius in one gather, no host
    synchronisation until the result is read; the support is that gather's count."""
    dx, dy = ring_offsets(radius)
    r, k, n = int(np.floor(radius)), int(max_neighbours), len(cols)
    width = int(np.max(cols)) + 1 + 2 * r
    x = torch.as_tensor(np.asarray(cols, dtype=np.int64), device=device)
    y = torch.as_tensor(np.asarray(rows, dtype=np.int64), device=device)
    v = torch.as_tensor(np.asarray(values, dtype=np.float64), device=device)
    flat = (y + r) * width + (x + r)
    index = torch.full(((int(np.max(rows)) + 1 + 2 * r) * width,), -1, dtype=torch.int32, device=device)
    index[flat] = torch.arange(n, dtype=torch.int32, device=device)
    steps = torch.as_tensor(dy * width + dx, dtype=torch.int64, device=device)
    neighbour = index[flat[:, None] + steps[None, :]]
    found = neighbour >= 0
    rank = torch.cumsum(found, dim=1)
    use = found & (rank <= k)
    # Column k collects what is not taken (scattered there, never read).
    taken = torch.full((n, k + 1), torch.inf, dtype=torch.float64, device=device)
    picked = torch.where(use, v[neighbour.clamp(min=0).long()], torch.inf)
    taken.scatter_(1, torch.where(use, rank - 1, k), picked)
    # One read back: the taken values and every point's neighbour count side by side.
    host = torch.cat((taken[:, :k], rank[:, -1:].to(torch.float64)), dim=1).cpu().numpy()
    within = host[:, k].astype(np.int64)
    count = np.minimum(within, k)
    return _median_of_rows(host[:, :k], count), count, within[::support_step]


def grid_counts(points: np.ndarray, sample: np.ndarray, radius: float) -> np.ndarray:
    """How many of ``points`` lie within ``radius`` (inclusive) of each ``sample`` point, itself
    and duplicates included, as ``cKDTree.query_ball_point(..., return_length=True)`` counts;
    every coordinate a non-negative integer (pixel positions; else a ValueError).

    Why: Ω's points are pixels, so the disk is a stack of row spans, each a difference of one
    row's cumulative sum of an occupancy image: (2r + 1) lookups per sample point and
    integers throughout, the same counts as the tree's ball query at a fraction of its cost
    (1.1 against 5.6 ms for 4096 queries among 8192 points on 2 cores).
    """
    if len(points) == 0 or len(sample) == 0:
        return np.zeros(len(sample), dtype=np.int64)
    pix, spix = points.astype(np.int64), sample.astype(np.int64)
    if not (np.array_equal(pix, points) and np.array_equal(spix, sample)) or pix.min() < 0 or spix.min() < 0:
        raise ValueError('grid_counts counts pixels: every coordinate must be a non-negative integer')
    r = int(np.floor(radius))
    height = int(max(pix[:, 1].max(), spix[:, 1].max())) + 1 + 2 * r
    width = int(max(pix[:, 0].max(), spix[:, 0].max())) + 2 + 2 * r  # a zero column left of x = 0
    flat = (pix[:, 1] + r) * width + pix[:, 0] + r + 1
    occupancy = np.bincount(flat, minlength=height * width).reshape(height, width)
    cumulative = np.cumsum(occupancy, axis=1)  # cumulative[y, x]: points in row y at columns <= x
    counts = np.zeros(len(sample), dtype=np.int64)
    cols, rows = spix[:, 0] + r + 1, spix[:, 1] + r
    for dy in range(-r, r + 1):
        half = math.isqrt(int(radius * radius - dy * dy))  # largest h with h^2 <= r^2 - dy^2
        counts += cumulative[rows + dy, cols + half] - cumulative[rows + dy, cols - half - 1]
    return counts


def _query_workers() -> int:
    """Threads for the k-d tree query: the process's torch threads. A node process started on
    its own gets one (``nodes/threads.py``: three processes share the cores), and a query split
    over two threads on a core another process holds waits for the descheduled half; ``evaluate``
    keeps one per core."""
    return max(1, torch.get_num_threads())
