"""Synthetic albedo: skin tones, procedural cloth and hair textures (no upstream textures exist).

Everything here is linear-light RGB in [0, 1], float32. Textures are square (T, T, 3) tiles
addressed by the garment's own OBJ UVs (v = 0 at the bottom row); `build_person` stacks the tiles
into one atlas. Patterns are painted in UV space, so stripes and checks follow each garment's
UV layout (seams may break a pattern, as on real garments).

Skin tones: the 10 swatches of the Monk Skin Tone scale (sRGB hex, Google, CC BY 4.0), decoded to
linear and scaled so the lightest is a plausible skin albedo (~0.6); a tone is drawn uniformly
along the scale (interpolated in linear light), so very light to very dark skin are equally
represented in the training data.
"""

from __future__ import annotations

import numpy as np

from relightcli.io.images import LUMINANCE, srgb_to_linear

MONK_SKIN_TONES_SRGB = ("f6ede4", "f3e7db", "f7ead0", "eadaba", "d7bd96",
                        "a07e56", "825c43", "604134", "3a312a", "292420")
SKIN_SCALE = 0.7
HAIR_COLOURS_SRGB = {  # natural and dyed hair, display colours
    "black": "1b1512", "dark_brown": "3b2a20", "brown": "6a4e3a", "auburn": "8d4a2b",
    "ginger": "b0632f", "dark_blonde": "9c7c53", "blonde": "d1b07a", "platinum": "e6dcc5",
    "grey": "9a9590", "white": "dedbd6",
}
PATTERNS = ("solid", "stripes", "checks", "print", "noise", "denim")


def hex_to_linear(code: str) -> np.ndarray:
    """`"rrggbb"` sRGB hex -> (3,) float32 linear RGB."""
    srgb = np.array([int(code[k:k + 2], 16) for k in (0, 2, 4)], dtype=np.float32) / 255.0
    return np.asarray(srgb_to_linear(srgb), dtype=np.float32)


def skin_palette() -> np.ndarray:
    """(10, 3) float32 linear skin albedos, lightest first."""
    return np.stack([hex_to_linear(c) for c in MONK_SKIN_TONES_SRGB]) * SKIN_SCALE


def skin_tone(t: float) -> np.ndarray:
    """Skin albedo (3,) float32 at position t in [0, 1] along the scale (0 lightest, 1 darkest)."""
    palette = skin_palette()
    x = np.clip(t, 0.0, 1.0) * (len(palette) - 1)
    k = min(int(x), len(palette) - 2)
    return ((1 - (x - k)) * palette[k] + (x - k) * palette[k + 1]).astype(np.float32)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 relative luminance of linear RGB (..., 3) -> (...)."""
    return rgb @ LUMINANCE.astype(rgb.dtype)


def smooth_noise(rng: np.random.Generator, size: int, octaves: tuple[int, ...] = (4, 8, 16, 32),
                 ) -> np.ndarray:
    """Fractal value noise (size, size) float32 in [0, 1]: bilinearly upsampled random grids."""
    total = np.zeros((size, size), dtype=np.float32)
    norm = 0.0
    for k, cells in enumerate(octaves):
        grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
        x = np.linspace(0, cells, size, dtype=np.float32)
        i = np.minimum(x.astype(int), cells - 1)
        f = x - i
        rows = grid[i] * (1 - f)[:, None] + grid[i + 1] * f[:, None]
        layer = rows[:, i] * (1 - f)[None, :] + rows[:, i + 1] * f[None, :]
        amp = 0.5 ** k
        total += amp * layer
        norm += amp
    total /= norm
    return (total - total.min()) / max(float(np.ptp(total)), 1e-6)


def random_cloth_colour(rng: np.random.Generator) -> np.ndarray:
    """A garment colour (3,) linear RGB: random hue, mixed saturation, value from dark to light."""
    h = rng.random()
    s = rng.choice([rng.uniform(0, 0.15), rng.uniform(0.2, 0.9)])  # greys and colours
    v = rng.uniform(0.08, 0.95)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    srgb = v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.clip(srgb_to_linear(srgb.astype(np.float32)), 0.01, 0.9).astype(np.float32)


def _uv_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.meshgrid((size - 0.5 - np.arange(size)) / size, (np.arange(size) + 0.5) / size,
                       indexing="ij")
    return u.astype(np.float32), v.astype(np.float32)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a[None, None, :] * (1 - t[..., None]) + b[None, None, :] * t[..., None]


def cloth_texture(rng: np.random.Generator, size: int,
                  pattern: str | None = None) -> tuple[np.ndarray, str]:
    """Procedural garment tile (size, size, 3) float32 linear in [0, 1] and its pattern name.

    pattern: one of PATTERNS (random when None). Folds (darkened creases from stretched noise)
    are painted on every pattern.
    """
    pattern = pattern or str(rng.choice(PATTERNS))
    if pattern not in PATTERNS:
        raise ValueError(f"unknown cloth pattern {pattern!r}; expected one of {PATTERNS}")
    a, b = random_cloth_colour(rng), random_cloth_colour(rng)
    u, v = _uv_grid(size)
    angle = rng.choice([0.0, np.pi / 2, rng.uniform(0, np.pi)])
    along = u * np.cos(angle) + v * np.sin(angle)
    freq = rng.uniform(8, 40)
    if pattern == "solid":
        tex = _mix(a, a, u)
    elif pattern == "stripes":
        tex = _mix(a, b, ((along * freq) % 1.0 < rng.uniform(0.2, 0.6)).astype(np.float32))
    elif pattern == "checks":
        su = ((u * freq) % 1.0 < 0.5).astype(np.float32)
        sv = ((v * freq) % 1.0 < 0.5).astype(np.float32)
        tex = _mix(a, b, 0.5 * (su + sv))  # gingham: half tone where one stripe set crosses
    elif pattern == "print":
        tex = _mix(a, a, u)
        for _ in range(int(rng.integers(40, 200))):
            cx, cy, r = rng.random(), rng.random(), rng.uniform(0.004, 0.03)
            dot = random_cloth_colour(rng) if rng.random() < 0.3 else b
            tex[(u - cx) ** 2 + (v - cy) ** 2 < r * r] = dot
    elif pattern == "noise":
        tex = _mix(a, b, smooth_noise(rng, size, (8, 16, 32, 64)))
    else:  # denim: blue-ish warp with a fine diagonal twill and fading
        blue = np.array([0.03, 0.06, 0.16], dtype=np.float32) * rng.uniform(0.6, 2.0)
        twill = 0.5 + 0.5 * np.sin((u + v) * size * 0.9)
        fade = smooth_noise(rng, size)
        tex = _mix(blue, blue * 2.5, 0.35 * twill + 0.65 * fade ** 2)
    tex = tex * fold_shading(rng, size)[..., None]
    return np.clip(tex, 0.0, 1.0).astype(np.float32), pattern


def fold_shading(rng: np.random.Generator, size: int, strength: float = 0.35) -> np.ndarray:
    """Multiplicative crease map (size, size) float32 in [1 - strength, 1]: thin dark ridges
    where warped low-frequency noise crosses level sets (wrinkles baked into the albedo)."""
    n = smooth_noise(rng, size, (3, 6, 12))
    ridges = np.abs(np.sin(n * rng.uniform(10, 25))) ** 0.3
    return (1.0 - strength * (1.0 - ridges)).astype(np.float32)


def paint_logo(rng: np.random.Generator, tex: np.ndarray, centre_uv: tuple[float, float]) -> None:
    """Paint a random geometric logo (disc, ring, bar or star) of ~6 % tile width in place."""
    size = tex.shape[0]
    u, v = _uv_grid(size)
    du, dv = u - centre_uv[0], v - centre_uv[1]
    r = np.hypot(du, dv)
    radius = rng.uniform(0.02, 0.05)
    kind = rng.choice(["disc", "ring", "bar", "star"])
    if kind == "disc":
        mask = r < radius
    elif kind == "ring":
        mask = (r < radius) & (r > 0.6 * radius)
    elif kind == "bar":
        mask = (np.abs(du) < radius * 1.5) & (np.abs(dv) < radius * 0.4)
    else:
        theta = np.arctan2(dv, du)
        mask = r < radius * (0.55 + 0.45 * np.cos(5 * theta))
    tex[mask] = random_cloth_colour(rng)


def skin_texture(rng: np.random.Generator, size: int, tone: np.ndarray) -> np.ndarray:
    """Skin tile (size, size, 3) float32: the tone with +-6 % blotchy variation and a slight
    red shift (blood) in places."""
    blotch = smooth_noise(rng, size, (8, 16, 32, 64)) - 0.5
    redness = smooth_noise(rng, size, (4, 8)) - 0.5
    tex = tone[None, None, :] * (1.0 + 0.12 * blotch[..., None])
    tex = tex * (1.0 + 0.08 * redness[..., None] * np.array([1.0, -0.5, -0.5], dtype=np.float32))
    return np.clip(tex, 0.0, 1.0).astype(np.float32)


def hair_texture(rng: np.random.Generator, size: int, colour: np.ndarray) -> np.ndarray:
    """Hair tile (size, size, 3) float32: strands as noise stretched along both UV axes
    (card UV orientation varies between hair meshes)."""
    streak = rng.random((4, size)).astype(np.float32)
    strands = 0.5 * (np.repeat(streak[:1], size, 0) + np.repeat(streak[1:2], size, 0).T)
    tex = colour[None, None, :] * (0.75 + 0.5 * strands[..., None])
    return np.clip(tex, 0.0, 1.0).astype(np.float32)


def sample_hair_colour(rng: np.random.Generator, age: float) -> tuple[str, np.ndarray]:
    """Hair colour name and (3,) linear albedo; grey/white more likely with MakeHuman age > 0.75."""
    names = list(HAIR_COLOURS_SRGB)
    p = np.ones(len(names))
    if age > 0.75:
        p[names.index("grey")] = p[names.index("white")] = 6.0
    name = str(rng.choice(names, p=p / p.sum()))
    return name, hex_to_linear(HAIR_COLOURS_SRGB[name]) * np.float32(rng.uniform(0.85, 1.1))


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup: texture (H, W, 3) float32, uv (N, 2) in [0, 1] with v = 0 at the bottom
    row (OBJ convention) -> (N, 3) float32. Coordinates are clamped to the texel centres."""
    h, w = texture.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0.0, w - 1.0)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(int), max(w - 2, 0))
    y0 = np.minimum(y.astype(int), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)
