"""Procedural, tileable, band-limited surface textures and their mip-mapped atlas.

The synthetic renderer attaches a texture to every surface in world (UV) coordinates so
that the same surface point has the same albedo in every view (what multi-view matching
needs). Textures are generated once per scene as images and sampled per pixel with
trilinear (mip-mapped bilinear) lookups, so

* no noise is evaluated per pixel per frame (rendering stays fast: all lookups of a frame
  are two ``cv2.remap`` calls into one packed atlas image), and
* a surface seen from far away is prefiltered to the pixel footprint instead of aliasing
  (aliasing would make the same point look different from different distances).

Every pattern is periodic on its square tile (built in the Fourier domain or from integer
frequencies), so tiling a wall with it shows no seams.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft

from ...point_lookup import bilinear_at

log = logging.getLogger(__name__)

#: Pattern kinds of strongly textured materials.
PATTERNS = ('noise', 'blobs', 'stripes', 'checker', 'speckle')


@lru_cache(maxsize=4)
def _frequency_radius(size: int) -> np.ndarray:
    """Radial frequency (cycles per texel) of each ``rfft2`` coefficient of a square tile."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    radius = np.hypot(fx, fy).astype(np.float32)
    radius.flags.writeable = False
    return radius


@lru_cache(maxsize=16)
def _band_amplitude(size: int, min_wavelength: float, max_wavelength: float, slope: float) -> np.ndarray:
    """Fourier amplitude of :func:`band_noise` (cached: a scene reuses a few bands)."""
    f = _frequency_radius(size)
    f_lo, f_hi = 1.0 / max_wavelength, 1.0 / min_wavelength
    power_law = np.where(f > 0, f, 1.0) ** np.float32(-slope)
    high_pass = (f / f_lo) ** 2 / (1.0 + (f / f_lo) ** 2)
    low_pass = np.exp(-((f / f_hi) ** 2))
    amplitude = (power_law * high_pass * low_pass).astype(np.float32)
    amplitude.flags.writeable = False
    return amplitude


def band_noise(
    rng: np.random.Generator, size: int, min_wavelength: float, max_wavelength: float, slope: float = 1.0
) -> np.ndarray:
    """Periodic noise with energy between two wavelengths (in texels), zero mean, unit std.

    Random Fourier coefficients shaped by ``f^-slope`` between a soft high-pass at
    ``1/max_wavelength`` and a Gaussian low-pass at ``1/min_wavelength``: the result is
    band-limited (no detail finer than ``min_wavelength``, hence no aliasing at level 0)
    and tiles seamlessly because the inverse FFT is periodic.
    """
    amplitude = _band_amplitude(size, float(min_wavelength), float(max_wavelength), float(slope))
    shape = amplitude.shape
    coeffs = rng.standard_normal(shape, dtype=np.float32) + 1j * rng.standard_normal(shape, dtype=np.float32)
    coeffs *= amplitude
    coeffs[0, 0] = 0.0
    noise = scipy.fft.irfft2(coeffs, s=(size, size))
    return (noise / max(float(noise.std()), 1e-12)).astype(np.float32)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _blur_periodic(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of a periodic (H, W) tile in the Fourier domain (keeps it tileable)."""
    f = _frequency_radius(image.shape[0])
    kernel = np.exp(-2.0 * (np.pi * sigma * f) ** 2)
    return scipy.fft.irfft2(scipy.fft.rfft2(image.astype(np.float32)) * kernel, s=image.shape).astype(
        np.float32
    )


def _integer_wave(rng: np.random.Generator, size: int, period: float) -> tuple[int, int]:
    """Integer frequencies ``(kx, ky)`` of a plane wave with roughly ``period`` texels and a
    random orientation; integer frequencies keep the wave periodic on the tile."""
    cycles = size / period
    angle = rng.uniform(0.0, np.pi)
    kx, ky = round(cycles * np.cos(angle)), round(cycles * np.sin(angle))
    if kx == 0 and ky == 0:
        kx = 1
    return kx, ky


def pattern(rng: np.random.Generator, kind: str, size: int) -> np.ndarray:
    """A periodic (size, size) float32 pattern in [0, 1] with content from ~4 to ~100 texels.

    The kinds mix strong edges (blobs, checker, stripes) with fine multi-scale detail (every
    kind adds some fine noise) so matching works on them at several image resolutions.
    """
    if kind not in PATTERNS:
        raise ValueError(f'unknown texture pattern {kind!r} (expected one of {", ".join(PATTERNS)})')
    fine = band_noise(rng, size, 3.0, 24.0, slope=0.5)
    y, x = (a.astype(np.float32) for a in np.ogrid[0:size, 0:size])
    if kind == 'noise':
        base = band_noise(rng, size, 4.0, 128.0, slope=1.0)
        p = 0.5 + 0.22 * base + 0.08 * fine
    elif kind == 'blobs':
        field = band_noise(rng, size, 12.0, 96.0, slope=1.0)
        p = 0.15 + 0.6 * _smoothstep((field - rng.uniform(-0.4, 0.4)) * 1.5 + 0.5) + 0.08 * fine
    elif kind == 'stripes':
        kx, ky = _integer_wave(rng, size, rng.uniform(10.0, 48.0))
        warp = band_noise(rng, size, 24.0, 160.0, slope=1.0)
        phase = 2.0 * np.pi * (kx * x + ky * y) / size + 0.9 * warp
        p = 0.5 + 0.3 * np.tanh(2.5 * np.sin(phase)) + 0.1 * fine
    elif kind == 'checker':
        cells = int(rng.integers(4, 16)) * 2
        wave = np.sin(np.pi * cells * x / size + 1e-3) * np.sin(np.pi * cells * y / size + 1e-3)
        p = 0.5 + 0.3 * np.tanh(4.0 * wave) + 0.1 * band_noise(rng, size, 3.0, 64.0, slope=0.8)
    else:  # speckle: granite-like dense detail at every small scale
        p = 0.5 + 0.18 * band_noise(rng, size, 3.0, 32.0, slope=0.3) + 0.08 * fine
    # Band limit at ~1 texel so level 0 itself is free of aliasing.
    return np.clip(_blur_periodic(p.astype(np.float32), 0.7), 0.0, 1.0)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """ITU-R 601 luma of linear RGB values in [0, 1] (last axis)."""
    return rgb @ np.array([0.299, 0.587, 0.114], dtype=rgb.dtype)


def random_colour(rng: np.random.Generator, lum_range: tuple[float, float]) -> np.ndarray:
    """A random saturated-ish RGB albedo whose luminance lies in ``lum_range``."""
    for _ in range(100):
        c = rng.uniform(0.05, 0.95, size=3).astype(np.float32)
        grey = float(luminance(c))
        c = grey + (c - grey) * rng.uniform(0.3, 1.0)  # desaturate a bit: rooms are not neon
        if lum_range[0] <= float(luminance(c)) <= lum_range[1]:
            return np.clip(c, 0.02, 0.98)
    target = float(np.mean(lum_range))
    return np.full(3, target, dtype=np.float32)


def _two_colours(rng: np.random.Generator, pattern_in_01) -> np.ndarray:
    """(S, S, 3) float32 albedo: the pattern ``pattern_in_01()`` (drawn after the colours, from
    the same ``rng``) blended between two colours of clearly different luminance (texture must
    survive conversion to grey)."""
    dark = random_colour(rng, (0.08, 0.35))
    light = random_colour(rng, (0.55, 0.9))
    p = pattern_in_01()[..., None]
    return (dark * (1.0 - p) + light * p).astype(np.float32)


def textured_albedo(rng: np.random.Generator, kind: str, size: int) -> np.ndarray:
    """(size, size, 3) float32 albedo of a :func:`pattern` kind."""
    return _two_colours(rng, lambda: pattern(rng, kind, size))


#: Texels of one period of a repetitive texture (a power of two: it divides every tile).
PERIOD_TEXELS = 32


def periodic_albedo(rng: np.random.Generator, size: int, cell: int = PERIOD_TEXELS) -> np.ndarray:
    """(size, size, 3) float32 albedo: one random motif of ``cell`` texels repeated on a square
    lattice, half the time framed by dark grout like tiles.

    Why: a wall of tiles, a brick wall or a bookshelf look the same again every period along
    an epipolar line, so a match one period off costs as little as the true one. Within a
    period the motif is as textured as :func:`pattern`'s kinds, so only the repetition is hard.
    """
    if size % cell:
        raise ValueError(f'a texture of {size} texels cannot repeat a motif of {cell}')

    def lattice() -> np.ndarray:
        motif = 0.5 + 0.22 * band_noise(rng, cell, 3.0, cell / 2.0, slope=0.8)
        if rng.uniform() < 0.5:  # grout: a dark frame round every tile
            edge = np.zeros(cell, dtype=bool)
            edge[:2] = True
            motif = np.where(edge[:, None] | edge[None, :], 0.1, motif)
        p = np.tile(motif.astype(np.float32), (size // cell, size // cell))
        return np.clip(_blur_periodic(p, 0.7), 0.0, 1.0)

    return _two_colours(rng, lattice)


def _mip_chain(level0: np.ndarray) -> list[np.ndarray]:
    """Box-filtered pyramid of a square power-of-two tile down to 1x1."""
    levels = [level0.astype(np.float32)]
    while levels[-1].shape[0] > 1:
        t = levels[-1]
        levels.append(0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2]))
    return levels


#: Width of the packed atlas image (cv2.remap needs image sides below 32767).
_ATLAS_WIDTH = 4096


def _shelf_pack(sizes: list[int], width: int) -> tuple[np.ndarray, int]:
    """Top-left corners (K, 2) of squares of side ``sizes`` packed on shelves of ``width``
    (largest first), and the total height used."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i])
    corners = np.zeros((len(sizes), 2), dtype=np.int64)
    x = y = shelf = 0
    for i in order:
        side = sizes[i]
        if side > width:
            raise ValueError(f'texture of {side} texels does not fit an atlas {width} wide')
        if x + side > width:
            x, y, shelf = 0, y + shelf, 0
        corners[i] = (x, y)
        x += side
        shelf = max(shelf, side)
    return corners, y + shelf


@dataclass
class TextureAtlas:
    """All mip levels of all textures of a scene packed in one float32 image.

    Each level is stored with a one-texel wrap-around border, so a plain bilinear lookup at
    any point of ``[-0.5, S - 0.5)`` is the periodic (tiled) lookup; then every sample of a
    frame, whatever its material and level, is served by one ``cv2.remap`` call per level
    set instead of per-texture gathers. Level ``l`` of texture ``t`` is ``sizes[t] >> l``
    texels wide and its first (non-border) texel is at ``origin[t, l]`` = (x, y).
    """

    image: np.ndarray  # (H, W, 3) float32 albedo in [0, 1]
    origin: np.ndarray  # (n_textures, max_levels, 2) float32
    sizes: np.ndarray  # (n_textures,) int64, power of two
    levels: np.ndarray  # (n_textures,) int64

    @classmethod
    def build(cls, textures: list[np.ndarray]) -> TextureAtlas:
        """Atlas of square power-of-two (S, S, 3) albedo textures in [0, 1] (a constant colour
        may be 1x1)."""
        chains = []
        for i, tex in enumerate(textures):
            s = tex.shape[0]
            if tex.ndim != 3 or tex.shape != (s, s, 3) or s & (s - 1):
                raise ValueError(
                    f'texture {i}: expected a square power-of-two (S, S, 3) array, got {tex.shape}'
                )
            chains.append(_mip_chain(np.clip(tex, 0.0, 1.0)))
        blocks = [(t, level, img) for t, chain in enumerate(chains) for level, img in enumerate(chain)]
        corners, height = _shelf_pack([img.shape[0] + 2 for _, _, img in blocks], _ATLAS_WIDTH)
        image = np.zeros((height, _ATLAS_WIDTH, 3), dtype=np.float32)
        origin = np.zeros((len(chains), max(len(c) for c in chains), 2), dtype=np.float32)
        for (t, level, img), (x, y) in zip(blocks, corners, strict=True):
            side = img.shape[0] + 2
            image[y : y + side, x : x + side] = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode='wrap')
            origin[t, level] = (x + 1, y + 1)
        sizes = np.array([c[0].shape[0] for c in chains], dtype=np.int64)
        levels = np.array([len(c) for c in chains], dtype=np.int64)
        return cls(image, origin, sizes, levels)

    @property
    def nbytes(self) -> int:
        return int(self.image.nbytes)

    def sample(self, tex: np.ndarray, u: np.ndarray, v: np.ndarray, lod: np.ndarray) -> np.ndarray:
        """Trilinear albedo samples (M, 3) float32 in [0, 1]: texture ids ``tex``, level-0
        texel coordinates ``(u, v)`` and level of detail ``lod`` = log2(texels per pixel), all
        (M,)."""
        if len(tex) == 0:
            return np.zeros((0, 3), dtype=np.float32)
        top = self.levels[tex] - 1
        lod = np.clip(np.nan_to_num(lod, nan=0.0), 0.0, None).astype(np.float32)
        lower = np.minimum(np.floor(lod).astype(np.int64), top)
        upper = np.minimum(lower + 1, top)
        frac = np.clip(lod - lower, 0.0, 1.0)[:, None].astype(np.float32)
        # The position within the tile, as a fraction, is the same at every level (sizes
        # are powers of two), so the wrap-around is computed once.
        inv_size = (1.0 / self.sizes.astype(np.float32))[tex]
        qu = u.astype(np.float32) * inv_size
        qv = v.astype(np.float32) * inv_size
        fu, fv = qu - np.floor(qu), qv - np.floor(qv)
        samples = []
        for level in (lower, upper):
            key = tex * self.origin.shape[1] + level
            side = self._side_table[key]
            corner = self._corner_table[key]
            samples.append(bilinear_at(self.image, corner[:, 0] + fu * side, corner[:, 1] + fv * side))
        return samples[0] * (1 - frac) + samples[1] * frac

    @property
    def _side_table(self) -> np.ndarray:
        """Side (texels) of every (texture, level), flat by ``texture * max_levels + level``."""
        levels = np.arange(self.origin.shape[1])
        return (self.sizes[:, None] >> levels[None, :]).astype(np.float32).reshape(-1)

    @property
    def _corner_table(self) -> np.ndarray:
        """Atlas coordinate of the first texel's left/top edge (centre - 0.5), flat like
        ``_side_table``."""
        return (self.origin - np.float32(0.5)).reshape(-1, 2)
