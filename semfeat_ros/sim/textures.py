"""Procedural texture building blocks, all evaluated at surface points so every view agrees.

* Tileable band-limited noise images (baked once per world from its seed) sampled bilinearly at
  world-space surface coordinates; each band is faded out where a pixel's footprint exceeds its
  wavelength (analytic anti-aliasing), so far surfaces do not sparkle.
* Integer hashes for per-cell randomness (bay stains, lit windows).
* A 5x7 bitmap font for sign and floor lettering.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

# --------------------------------------------------------------------------------------- hashes


def hash_u32(*keys: np.ndarray) -> np.ndarray:
    """Deterministic 32-bit integer hash of integer arrays (broadcast), as uint32."""
    h = np.uint32(0x9E3779B9)
    out = None
    for k in keys:
        v = np.asarray(k).astype(np.int64).astype(np.uint32)
        x = v if out is None else out ^ (v + h + (out << np.uint32(6)) + (out >> np.uint32(2)))
        x = x ^ (x >> np.uint32(16))
        x = x * np.uint32(0x7FEB352D)
        x = x ^ (x >> np.uint32(15))
        x = x * np.uint32(0x846CA68B)
        out = x ^ (x >> np.uint32(16))
    return out if out is not None else np.uint32(0)


def hash_unit(*keys: np.ndarray) -> np.ndarray:
    """Hash of integer arrays mapped to float32 in [0, 1)."""
    return (hash_u32(*keys) >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


# ------------------------------------------------------------------------------------- textures


def _tileable_noise(rng: np.random.Generator, size: int, sigma: float) -> np.ndarray:
    """Zero-mean, unit-std periodic noise image (size x size) with correlation length sigma px."""
    img = gaussian_filter(rng.standard_normal((size, size)), sigma, mode='wrap')
    img -= img.mean()
    img /= img.std() + 1e-12
    return img.astype(np.float32)


def _cracks(rng: np.random.Generator, size: int, n: int, length: int) -> np.ndarray:
    """Periodic image in [0, 1] with ``n`` thin wandering crack lines."""
    img = np.zeros((size, size), np.float32)
    for _ in range(n):
        x, y = rng.uniform(0, size, 2)
        ang = rng.uniform(0, 2 * np.pi)
        steps = int(rng.integers(length // 3, length))
        for _ in range(steps):
            ang += rng.normal(0, 0.25)
            x += np.cos(ang) * 0.8
            y += np.sin(ang) * 0.8
            img[int(y) % size, int(x) % size] = 1.0
            if rng.random() < 0.02:  # branch stub
                ang += rng.choice([-1.0, 1.0]) * 0.9
    img = gaussian_filter(img, 0.55, mode='wrap')
    return np.clip(img / (img.max() + 1e-9) * 1.6, 0.0, 1.0).astype(np.float32)


def _blobs(rng: np.random.Generator, size: int) -> np.ndarray:
    """Periodic soft-edged blotch image in [0, 1] (stains, damp patches)."""
    n = _tileable_noise(rng, size, size / 24.0)
    fine = _tileable_noise(rng, size, size / 96.0)
    v = n + 0.35 * fine
    return np.clip((v - 0.9) * 1.6, 0.0, 1.0).astype(np.float32)


_OFFSET = np.float32(65536.0)  # keeps texel coordinates positive (|s| < 65536 texels)


@dataclass(frozen=True)
class Band:
    """A tileable texture sampled at ``texel`` metres per texel.

    ``image`` is (S+1, S+1) float32: a power-of-two periodic image with its first row and
    column repeated at the end, so bilinear lookups need no wrap of the second index.
    """

    image: np.ndarray
    texel: float  # m

    @staticmethod
    def from_periodic(img: np.ndarray, texel: float) -> Band:
        """Wrap-pad a square power-of-two periodic image."""
        size = img.shape[0]
        if img.shape != (size, size) or size & (size - 1):
            raise ValueError(f'band image must be square power-of-two, got {img.shape}')
        return Band(np.pad(img, ((0, 1), (0, 1)), mode='wrap').astype(np.float32), texel)

    def sample(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Bilinear periodic lookup at surface coordinates ``s, t`` (m), float32."""
        inv = np.float32(1.0 / self.texel)
        return sample_periodic(self.image, s * inv, t * inv)


def sample_periodic(padded: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around at texel coordinates in a wrap-padded image."""
    size = padded.shape[0] - 1
    mask = size - 1
    stride = size + 1
    s = np.asarray(s, dtype=np.float32) + _OFFSET
    t = np.asarray(t, dtype=np.float32) + _OFFSET
    i0 = s.astype(np.int32)
    j0 = t.astype(np.int32)
    a = s - i0.astype(np.float32)
    b = t - j0.astype(np.float32)
    idx = (j0 & mask) * stride + (i0 & mask)
    flat = padded.ravel()
    v00 = flat.take(idx)
    v01 = flat.take(idx + 1)
    idx += stride
    v10 = flat.take(idx)
    v11 = flat.take(idx + 1)
    top = v00 + a * (v01 - v00)
    bot = v10 + a * (v11 - v10)
    return top + b * (bot - top)


@dataclass(frozen=True)
class TextureBank:
    """The baked noise bands of one world."""

    fine: Band  # speckle / aggregate, ~2 cm
    mid: Band  # blotches, ~10-30 cm
    coarse: Band  # large stains and tone variation, ~1-4 m
    crack: Band  # thin cracks
    blob: Band  # soft stains (oil, damp)
    cloud: Band  # cloud cover in [0, 1] on the sky dome (texel = 1 unit of dome coords)

    def noise(self, s: np.ndarray, t: np.ndarray, footprint: np.ndarray,
              weights: tuple[float, float, float]) -> np.ndarray:
        """Multi-band noise (zero mean) at surface coordinates; bands finer than the pixel
        footprint (m) are faded out."""
        w_fine, w_mid, w_coarse = weights
        out = w_coarse * self.coarse.sample(s * 0.93 + 17.3, t * 0.93 - 5.1)
        if w_mid:
            fade = np.clip(2.0 - footprint * (1.0 / (3.0 * self.mid.texel)), 0.0, 1.0)
            out = out + (w_mid * fade) * self.mid.sample(s, t)
        if w_fine:
            fade = np.clip(2.0 - footprint * (1.0 / (2.5 * self.fine.texel)), 0.0, 1.0)
            out = out + (w_fine * fade) * self.fine.sample(s + 3.7, t + 1.3)
        return out

    def cracks(self, s: np.ndarray, t: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Crack darkness in [0, 1], faded with the footprint."""
        fade = np.clip(2.0 - footprint * (1.0 / (4.0 * self.crack.texel)), 0.0, 1.0)
        return fade * self.crack.sample(s, t)


def make_texture_bank(seed: int) -> TextureBank:
    """Bake the noise bands of a world (deterministic in ``seed``; ~0.5 s)."""
    rng = np.random.default_rng([seed, 0x7E7])
    fine = _tileable_noise(rng, 256, 0.8)
    mid = _tileable_noise(rng, 256, 3.0)
    coarse = _tileable_noise(rng, 128, 4.0)
    crack = _cracks(rng, 512, 9, 300)
    blob = _blobs(rng, 256)
    cloud_n = _tileable_noise(rng, 256, 10.0) + 0.5 * _tileable_noise(rng, 256, 3.0)
    cloud = np.clip((cloud_n - 0.3) * 0.8, 0.0, 1.0).astype(np.float32)
    return TextureBank(
        fine=Band.from_periodic(fine, 0.015), mid=Band.from_periodic(mid, 0.05),
        coarse=Band.from_periodic(coarse, 0.35), crack=Band.from_periodic(crack, 0.02),
        blob=Band.from_periodic(blob, 0.06), cloud=Band.from_periodic(cloud, 1.0))


# ----------------------------------------------------------------------------------------- font

_FONT_ROWS = {
    ' ': ['.....'] * 7,
    '0': ['.###.', '#...#', '#..##', '#.#.#', '##..#', '#...#', '.###.'],
    '1': ['..#..', '.##..', '..#..', '..#..', '..#..', '..#..', '.###.'],
    '2': ['.###.', '#...#', '....#', '...#.', '..#..', '.#...', '#####'],
    '3': ['####.', '....#', '....#', '.###.', '....#', '....#', '####.'],
    '4': ['...#.', '..##.', '.#.#.', '#..#.', '#####', '...#.', '...#.'],
    '5': ['#####', '#....', '####.', '....#', '....#', '#...#', '.###.'],
    '6': ['..##.', '.#...', '#....', '####.', '#...#', '#...#', '.###.'],
    '7': ['#####', '....#', '...#.', '..#..', '.#...', '.#...', '.#...'],
    '8': ['.###.', '#...#', '#...#', '.###.', '#...#', '#...#', '.###.'],
    '9': ['.###.', '#...#', '#...#', '.####', '....#', '...#.', '.##..'],
    'A': ['.###.', '#...#', '#...#', '#####', '#...#', '#...#', '#...#'],
    'B': ['####.', '#...#', '#...#', '####.', '#...#', '#...#', '####.'],
    'C': ['.###.', '#...#', '#....', '#....', '#....', '#...#', '.###.'],
    'D': ['####.', '#...#', '#...#', '#...#', '#...#', '#...#', '####.'],
    'E': ['#####', '#....', '#....', '####.', '#....', '#....', '#####'],
    'F': ['#####', '#....', '#....', '####.', '#....', '#....', '#....'],
    'H': ['#...#', '#...#', '#...#', '#####', '#...#', '#...#', '#...#'],
    'I': ['.###.', '..#..', '..#..', '..#..', '..#..', '..#..', '.###.'],
    'K': ['#...#', '#..#.', '#.#..', '##...', '#.#..', '#..#.', '#...#'],
    'L': ['#....', '#....', '#....', '#....', '#....', '#....', '#####'],
    'M': ['#...#', '##.##', '#.#.#', '#.#.#', '#...#', '#...#', '#...#'],
    'N': ['#...#', '##..#', '#.#.#', '#..##', '#...#', '#...#', '#...#'],
    'O': ['.###.', '#...#', '#...#', '#...#', '#...#', '#...#', '.###.'],
    'P': ['####.', '#...#', '#...#', '####.', '#....', '#....', '#....'],
    'R': ['####.', '#...#', '#...#', '####.', '#.#..', '#..#.', '#...#'],
    'S': ['.####', '#....', '#....', '.###.', '....#', '....#', '####.'],
    'T': ['#####', '..#..', '..#..', '..#..', '..#..', '..#..', '..#..'],
    'U': ['#...#', '#...#', '#...#', '#...#', '#...#', '#...#', '.###.'],
    'V': ['#...#', '#...#', '#...#', '#...#', '#...#', '.#.#.', '..#..'],
    'W': ['#...#', '#...#', '#...#', '#.#.#', '#.#.#', '##.##', '#...#'],
    'X': ['#...#', '#...#', '.#.#.', '..#..', '.#.#.', '#...#', '#...#'],
    'Y': ['#...#', '#...#', '.#.#.', '..#..', '..#..', '..#..', '..#..'],
    'm': ['.....', '.....', '##.#.', '#.#.#', '#.#.#', '#.#.#', '#.#.#'],
    '.': ['.....', '.....', '.....', '.....', '.....', '.##..', '.##..'],
    '-': ['.....', '.....', '.....', '#####', '.....', '.....', '.....'],
    '>': ['..#..', '...#.', '....#', '#####', '....#', '...#.', '..#..'],
    '<': ['..#..', '.#...', '#....', '#####', '#....', '.#...', '..#..'],
    '^': ['..#..', '.###.', '#.#.#', '..#..', '..#..', '..#..', '..#..'],
    '!': ['..#..', '..#..', '..#..', '..#..', '..#..', '.....', '..#..'],
}

FONT_CHARS = ''.join(_FONT_ROWS)
"""Characters the sign font can draw."""

FONT = np.array([[[c == '#' for c in row] for row in _FONT_ROWS[ch]] for ch in FONT_CHARS],
                dtype=bool)
"""(n_chars, 7, 5) glyph bitmaps, row 0 at the top."""


def encode_text(text: str, length: int) -> np.ndarray:
    """Font indices of ``text`` padded with spaces to ``length`` (int16)."""
    bad = sorted(set(text) - set(FONT_CHARS))
    if bad:
        raise ValueError(f'text {text!r}: characters {bad} are not in the sign font')
    codes = [FONT_CHARS.index(c) for c in text.ljust(length)[:length]]
    return np.array(codes, dtype=np.int16)


def glyph_mask(codes: np.ndarray, n_chars: np.ndarray, s: np.ndarray, t: np.ndarray,
               margin: float | np.ndarray = 0.12) -> np.ndarray:
    """Ink mask of text drawn in a unit rectangle.

    Args:
        codes: (N, L) font indices of each point's text.
        n_chars: (N,) number of characters of each text (<= L).
        s, t: (N,) position in the rectangle, s in [0, 1] left to right, t in [0, 1] top to
            bottom.
        margin: blank border (fraction of the rectangle), scalar or (N,).
    """
    inner = 1.0 - 2.0 * margin
    su = (s - margin) / inner
    tu = (t - margin) / inner
    inside = (su >= 0) & (su < 1) & (tu >= 0) & (tu < 1)
    n = np.maximum(n_chars, 1)
    cell = np.clip(np.floor(su * n), 0, n - 1).astype(np.int64)
    cs = su * n - cell  # in [0, 1) within the character cell (with 1/6 spacing)
    col = np.clip(np.floor(cs * 6.0), 0, 5).astype(np.int64)
    row = np.clip(np.floor(tu * 7.0), 0, 6).astype(np.int64)
    code = np.take_along_axis(codes, np.clip(cell, 0, codes.shape[1] - 1)[:, None], 1)[:, 0]
    ink = FONT[code, row, np.minimum(col, 4)] & (col < 5)
    return inside & ink
