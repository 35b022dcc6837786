"""An environment map as a light: radiance lookup and importance sampling, built once per map.

Directions follow relightcli.io.envmap (the single source of truth); radiance is linear RGB,
float32 (H, W, 3) with W = 2H. Lookups are nearest-texel. The sampling distribution is
piecewise constant over cells of cell x cell texels (1 by default: per texel, the function
`eval` looks up, so `eval / pdf` is exact per texel), proportional to each cell's energy and
uniform in (u, v) within it; a sky is sampled over larger cells (`sampling_cell`), whose
small tables stay in cache.
"""

from __future__ import annotations

import functools

import numpy as np

from relightcli.errors import InputError
from relightcli.io.envmap import (
    direction_to_uv,
    repair_radiance,
    resample_envmap,
    texel_solid_angles,
    uv_to_direction,
)
from relightcli.render.sampling import guide_table, search_cdf

# Share of the energy in the brightest 0.1% of texels above which a map is "one sun disc"
SUN_ENERGY_FRACTION = 0.999
# Relative spread below which a map counts as constant
CONSTANT_TOLERANCE = 1e-6
# Unoccluded-shading table: normals on NODES + 1 rows (poles included) x 2 TEXEL_ROWS
# columns, summed over the map area-resampled to TEXEL_ROWS x 2 TEXEL_ROWS texels. Bilinear
# lookups are within 0.5% of the full-resolution sum on studio, sun and overcast maps (tested).
IRRADIANCE_NODES = 128
IRRADIANCE_TEXEL_ROWS = 64
# A sky (no sun in it) is sampled over cells of texels, uniform in (u, v) within a cell, with
# at least this many rows of cells: a small table the sampling's random lookups find in cache
SAMPLING_ROWS = 128
# Sampling's guide table (relightcli.render.sampling.guide_table): buckets per lit cell, up to
# a size that stays in cache (2 MB)
GUIDE_BUCKETS_PER_CELL = 16
GUIDE_MAX_BUCKETS = 1 << 19


def sanitize_radiance(radiance) -> np.ndarray:
    """(H, W, 3) float32, finite and >= 0, by the maps' one rule (io.envmap.repair_radiance:
    NaN, -Inf and negatives -> 0, +Inf -> the largest finite value; warns when it repairs)."""
    radiance = np.asarray(radiance, dtype=np.float32)
    if radiance.ndim != 3 or radiance.shape[2] != 3 or radiance.shape[0] < 1:
        raise InputError(
            f"environment map must be (H, W, 3), got shape {radiance.shape}",
            fix="pass an equirectangular RGB map with W = 2H",
        )
    return np.ascontiguousarray(repair_radiance(radiance, stacklevel=3), dtype=np.float32)


class EnvironmentLight:
    """Radiance lookup and a sampling distribution proportional to mean-RGB radiance x sin(theta).

    radiance: (H, W, 3) linear RGB; cell: the side of the square blocks of texels sampling
    picks from (dividing H and W). The distribution over texel coordinates (u, v) folds in the
    texel solid angle (exact per-row, proportional to sin(theta)), summed per cell; `pdf`
    converts back to solid angle by dividing by 2 pi^2 sin(theta). Sampling inverts one cdf
    over the lit cells in row-major order (u[0] picks the cell and its column offset, u[1]
    the row offset): one search per sample, over only the sun's texels for a sun.
    """

    def __init__(self, radiance, cell: int = 1):
        self.radiance = sanitize_radiance(radiance)
        height, width, _ = self.radiance.shape
        if cell < 1 or height % cell or width % cell:
            raise ValueError(f"cell must divide the map's {height}x{width} texels, got {cell}")
        energy = _channel_mean(self.radiance).astype(np.float64) * texel_solid_angles(height, width)
        self.total_energy = float(energy.sum())
        self.is_black = self.total_energy <= 0.0
        if self.is_black:
            energy = np.ones_like(energy)  # sampling stays defined: uniform over the texels
        # Sampling cells: blocks of cell x cell texels, uniform in (u, v) within each
        self.cell = cell
        rows, cols = height // cell, width // cell
        cell_energy = energy.reshape(rows, cell, cols, cell).sum(axis=(1, 3))
        # Density over (u, v) in [0, 1)^2 per cell, and the cdf over the lit cells
        self.cell_pdf_uv = cell_energy / cell_energy.mean()
        self._lit = np.flatnonzero(cell_energy.ravel() > 0)
        cdf = np.cumsum(cell_energy.ravel()[self._lit])
        self._cdf = np.concatenate([[0.0], cdf / cdf[-1]])
        self._cdf[-1] = 1.0
        # What sampling reads per lit cell, gathered once: row, column, density (and radiance
        # for single-texel cells)
        self._lit_row, self._lit_col = (a.astype(np.int32) for a in np.divmod(self._lit, cols))
        self._lit_pdf_uv = self.cell_pdf_uv.ravel()[self._lit]
        flat = self.radiance.reshape(-1, 3)
        # np.take and per-channel loops: numpy's reductions and fancy indexing along a
        # 3-long inner axis are 5-25x slower on a 512 x 1024 map, for the same values
        self._lit_radiance = np.take(flat, self._lit, axis=0) if cell == 1 else None
        self._guide = None  # search_cdf's guide over _cdf, built on the first sample
        channels = [self.radiance[..., c] for c in range(3)]
        top = np.array([c.max() for c in channels])
        spread = top - np.array([c.min() for c in channels])
        self.is_constant = bool(np.all(spread <= CONSTANT_TOLERANCE * np.maximum(top, 1e-30)))
        self.constant_radiance = flat.mean(axis=0).astype(np.float64) if self.is_constant else None
        self.sun_fraction = _top_energy_fraction(energy, 0.001)
        # Share of the sphere (by solid angle) whose texels are black in every channel
        solid = texel_solid_angles(height, width)
        black = ~((channels[0] > 0) | (channels[1] > 0) | (channels[2] > 0))
        self.black_fraction = float(solid[black].sum() / solid.sum())
        self.is_sun_only = (not self.is_black) and self.sun_fraction >= SUN_ENERGY_FRACTION
        self._sun_and_sky = None
        self._coarse = None
        # Built on first use, shared with the coarse_sampling() copy: "irradiance"
        self._tables = {}

    def irradiance(self, normals) -> np.ndarray:
        """Unoccluded shading (1/pi) integral of L(w) max(0, n.w) dw (DESIGN.md units) for unit
        normals (N, 3): (N, 3) float64, bilinear in a table built on first use."""
        if "irradiance" not in self._tables:
            self._tables["irradiance"] = _irradiance_table(self.radiance, IRRADIANCE_NODES,
                                                           IRRADIANCE_TEXEL_ROWS)
        return lookup_normal_table(self._tables["irradiance"], normals)

    def coarse_sampling(self):
        """This light sampled over cells of texels (`sampling_cell`) instead of single
        texels: the same radiance and irradiance table, a small sampling table. Cached."""
        cell = sampling_cell(*self.radiance.shape[:2])
        if cell == self.cell:
            return self
        if self._coarse is None:
            self._coarse = EnvironmentLight(self.radiance, cell)
            self._coarse._tables = self._tables  # one irradiance table for both
        return self._coarse

    def sun_and_sky(self):
        """`split_sun()`, computed once per light (renders of a turntable reuse it)."""
        if self._sun_and_sky is None:
            self._sun_and_sky = self.split_sun()
        return self._sun_and_sky

    def split_sun(self, share: float = 0.001):
        """(sun, sky): two lights whose radiances sum to this one's. The sun holds the
        brightest `share` of texels by energy, the sky the rest, so each can be sampled
        on its own: the choice between sun and sky then adds no variance. The sun is sampled
        texel by texel, the sky over cells (`sampling_cell`)."""
        energy = _channel_mean(self.radiance) * texel_solid_angles(*self.radiance.shape[:2])
        count = max(1, int(round(share * energy.size)))
        threshold = np.partition(energy.ravel(), energy.size - count)[energy.size - count]
        in_sun = (energy >= threshold) & (energy > 0)
        sun = np.where(in_sun[..., None], self.radiance, np.float32(0.0))
        sky = np.where(in_sun[..., None], np.float32(0.0), self.radiance)
        return EnvironmentLight(sun), EnvironmentLight(sky, sampling_cell(*sky.shape[:2]))

    @property
    def shape(self):
        return self.radiance.shape

    def eval(self, directions) -> np.ndarray:
        """Radiance (..., 3) float32 arriving from unit directions (..., 3) (nearest texel)."""
        u, v = direction_to_uv(directions)
        return self.radiance[self._row(v), self._col(u)]

    def sample(self, u):
        """Directions (..., 3) float64 and solid-angle pdfs (...) float64 from u (..., 2)."""
        directions, pdf, _ = self.sample_radiance(u)
        return directions, pdf

    def sample_radiance(self, u, dtype=np.float64):
        """`sample`, plus the radiance (..., 3) float32 from each sampled direction (read
        from the sampled texel, no second lookup). dtype: the directions' precision; the
        renderer asks for float32 (what the tracer takes; trig ~10x faster), which changes
        directions and the pdf's sin(theta) by float32 round-off, never the texel."""
        u = np.asarray(u, dtype=np.float64)
        height, width, _ = self.radiance.shape
        cell = self.cell
        u0 = np.minimum(u[..., 0], np.nextafter(1.0, 0.0))
        u1 = u[..., 1]
        if self._guide is None:
            cells = self._cdf.size - 1
            self._guide = guide_table(self._cdf, max(cells, min(GUIDE_BUCKETS_PER_CELL * cells, GUIDE_MAX_BUCKETS)))
        k = np.clip(search_cdf(self._cdf, u0, self._guide), 0, self._lit.size - 1)
        lo = self._cdf[k]
        span = self._cdf[k + 1] - lo
        offset = np.clip((u0 - lo) / np.where(span > 0, span, 1.0), 0.0, 1.0)
        row, col = np.take(self._lit_row, k), np.take(self._lit_col, k)
        x = np.minimum((col + offset) * (cell / width), np.nextafter(1.0, 0.0))
        y = np.minimum((row + u1) * (cell / height), np.nextafter(1.0, 0.0))
        directions = uv_to_direction(x, y, dtype)
        pdf = _uv_pdf_to_solid_angle(np.take(self._lit_pdf_uv, k), _sin_theta(directions))
        if cell == 1:
            return directions, pdf, np.take(self._lit_radiance, k, axis=0)
        # The texel within the cell, from the same offsets that placed the direction
        texel_row = row * cell + np.minimum((u1 * cell).astype(np.int32), cell - 1)
        texel_col = col * cell + np.minimum((offset * cell).astype(np.int32), cell - 1)
        return directions, pdf, np.take(self.radiance.reshape(-1, 3), texel_row * width + texel_col, axis=0)

    def eval_pdf(self, directions):
        """(`eval`, `pdf`) of unit directions (..., 3) with a single direction lookup."""
        u, v = direction_to_uv(directions)
        row, col = self._row(v), self._col(u)
        return (np.take(self.radiance.reshape(-1, 3), row * self.radiance.shape[1] + col, axis=0),
                _uv_pdf_to_solid_angle(np.take(self.cell_pdf_uv, self._cell_index(row, col)),
                                       _sin_theta(directions)))

    def pdf(self, directions) -> np.ndarray:
        """Solid-angle pdf (...) float64 of `sample` producing unit directions (..., 3)."""
        u, v = direction_to_uv(directions)
        return _uv_pdf_to_solid_angle(np.take(self.cell_pdf_uv, self._cell_index(self._row(v), self._col(u))),
                                      _sin_theta(directions))

    def invert_sample(self, directions) -> np.ndarray:
        """The u (..., 2) that `sample` maps to unit directions (..., 3)."""
        u, v = direction_to_uv(directions)
        height, width, _ = self.radiance.shape
        rows, cols = height // self.cell, width // self.cell
        row = np.clip((np.asarray(v) * rows).astype(np.int64), 0, rows - 1)
        col = np.clip((np.asarray(u) * cols).astype(np.int64), 0, cols - 1)
        k = np.clip(np.searchsorted(self._lit, row * cols + col), 0, self._lit.size - 1)
        offset = np.clip(u * cols - col, 0.0, 1.0)
        u0 = self._cdf[k] + offset * (self._cdf[k + 1] - self._cdf[k])
        return np.stack([u0, np.clip(v * rows - row, 0.0, 1.0)], axis=-1)

    def _cell_index(self, row, col):
        """Flat index into cell_pdf_uv of texel rows and columns."""
        if self.cell == 1:
            return row * self.radiance.shape[1] + col
        return (row // self.cell) * (self.radiance.shape[1] // self.cell) + col // self.cell

    def _row(self, v):
        height = self.radiance.shape[0]
        return np.clip((np.asarray(v) * height).astype(np.int64), 0, height - 1)

    def _col(self, u):
        width = self.radiance.shape[1]
        return np.clip((np.asarray(u) * width).astype(np.int64), 0, width - 1)


class TabulatedSampling:
    """`light` with its samples drawn ahead: one sample at a uniform random point of each cell
    of a `shape` = (m, n) grid over the unit square of `sample_radiance`'s u (m along u[0],
    which picks the map's cell, n along u[1]), drawn once by `rng`; `sample_radiance` returns
    the sample of the cell its u falls in: a gather instead of a cdf search and a direction
    per sample.

    Unbiased: over the draw, the point behind the sample of a u is uniform in u's cell, so for
    a uniform u the sample is distributed as the light's own (its pdf and radiance are the
    light's). The shared draw adds an error common to every pixel, that of a stratified
    estimate over m x n strata, small against a pixel's own at the sample counts rendered
    (the integrator's tests check the reported error with and without a table). `eval_pdf`, the
    lookup of given directions that MIS needs, is the light's."""

    def __init__(self, light: EnvironmentLight, shape: tuple, rng: np.random.Generator):
        self.light, self.shape = light, (int(shape[0]), int(shape[1]))
        self.black_fraction = light.black_fraction
        first, second = self.shape
        corner = np.stack(np.divmod(np.arange(first * second), second), axis=1).astype(np.float64)
        u = (corner + rng.random(corner.shape)) / np.array(self.shape, np.float64)
        self.directions, self.pdf_table, self.radiance_table = light.sample_radiance(u, np.float32)

    def sample_radiance(self, u, dtype=np.float32):
        """`EnvironmentLight.sample_radiance` from the table: directions in float32 (cast to
        `dtype`), pdfs float64, radiance float32."""
        u = np.asarray(u, dtype=np.float64)
        first, second = self.shape
        index = (np.minimum((u[..., 0] * first).astype(np.int64), first - 1) * second
                 + np.minimum((u[..., 1] * second).astype(np.int64), second - 1))
        directions = np.take(self.directions, index, axis=0)
        return (directions if dtype == np.float32 else directions.astype(dtype),
                np.take(self.pdf_table, index), np.take(self.radiance_table, index, axis=0))

    def eval_pdf(self, directions):
        return self.light.eval_pdf(directions)


def sampling_cell(height: int, width: int) -> int:
    """The side of the texel cells a sky is sampled over: the largest power of two that
    divides both sides and leaves at least SAMPLING_ROWS rows of cells (1 for small maps)."""
    cell = 1
    while height % (2 * cell) == 0 and width % (2 * cell) == 0 and height // (2 * cell) >= SAMPLING_ROWS:
        cell *= 2
    return cell


def lookup_normal_table(table: np.ndarray, normals) -> np.ndarray:
    """Bilinear lookup of a (rows + 1, width, ...) table over unit normals on the node grid
    u = j / width, v = i / rows (rows 0 and `rows` are the poles), at normals (N, 3):
    (N, ...), wrapping in u."""
    u, v = direction_to_uv(np.asarray(normals, dtype=np.float64))
    rows, width = table.shape[0] - 1, table.shape[1]
    x, y = u * width, np.clip(v * rows, 0.0, rows)
    col0, row0 = np.floor(x), np.minimum(np.floor(y), rows - 1)
    extra = (1,) * (table.ndim - 2)
    # the weights in the table's precision: a float32 table is blended in float32
    fx, fy = ((f.astype(table.dtype) if table.dtype.kind == "f" else f).reshape(-1, *extra)
              for f in (x - col0, y - row0))
    col0 = col0.astype(np.int64) % width
    col1, row0 = (col0 + 1) % width, row0.astype(np.int64)
    top = table[row0, col0]
    top += fx * (table[row0, col1] - top)
    bottom = table[row0 + 1, col0]
    bottom += fx * (table[row0 + 1, col1] - bottom)
    top += fy * (bottom - top)
    return top


def _irradiance_table(radiance, nodes, texel_rows):
    """(nodes + 1, 2 texel_rows, 3) float64 unoccluded shading at normals on the node grid
    u = j / (2 texel_rows), v = i / nodes (rows 0 and `nodes` are the poles).

    The map is area-resampled to texel_rows x 2 texel_rows (up or down). Turning a normal about the pole
    axis turns the clamped cosine with it, so each (normal row, texel row) pair is a circular
    correlation along u, done with FFTs; the clamped cosine is integrated exactly across each
    texel column (the terminator cuts through columns), sampled at the texel row's centre.
    """
    coarse = resample_envmap(radiance, texel_rows).astype(np.float64)  # (rows, width, 3)
    # E[i, j] = sum_t sum_k L[t, k] K[i, t, (k - j) mod width]
    spectrum = np.einsum("tfc,itf->ifc", np.fft.rfft(coarse, axis=1), _cosine_kernel_spectrum(nodes, texel_rows))
    return np.fft.irfft(spectrum, n=2 * texel_rows, axis=1)


def irradiance_kernel() -> np.ndarray:
    """The kernel of every irradiance table (`_cosine_kernel_spectrum` on the default grid),
    computed and kept: a process that will trace rays asks for it ahead (pipeline.prepared_models)."""
    return _cosine_kernel_spectrum(IRRADIANCE_NODES, IRRADIANCE_TEXEL_ROWS)


@functools.lru_cache(maxsize=4)
def _cosine_kernel_spectrum(nodes: int, texel_rows: int) -> np.ndarray:
    """(nodes + 1, texel_rows, texel_rows + 1) complex: the conjugate spectrum along u of the
    clamped-cosine kernel of `_irradiance_table`, which depends on the grid only (kept: 80% of
    a table's time)."""
    rows = texel_rows  # small maps are resampled up (in blocks): the quadrature needs the rows
    width = 2 * rows
    solid = texel_solid_angles(rows, width)[:, 0] / np.pi  # (rows,) per texel, over pi
    theta_t = np.pi * (np.arange(rows) + 0.5) / rows
    theta_n = np.pi * np.arange(nodes + 1) / nodes
    a = np.cos(theta_n)[:, None, None] * np.cos(theta_t)[None, :, None]
    b = np.sin(theta_n)[:, None, None] * np.sin(theta_t)[None, :, None]
    # Column m of the kernel covers azimuth offsets [m, m + 1] x step (m >= width/2 wraps)
    step = 2.0 * np.pi / width
    m = np.arange(width)
    lo = np.where(m < width // 2, m, m - width)[None, None, :] * step
    hi = lo + step
    # a + b cos(phi) > 0 for |phi| < phi_c
    ratio = np.divide(-a, b, out=np.where(a > 0, -2.0, 2.0), where=b > 0)
    phi_c = np.arccos(np.clip(ratio, -1.0, 1.0))
    lo_c, hi_c = np.maximum(lo, -phi_c), np.minimum(hi, phi_c)
    kernel = np.where(hi_c > lo_c, a * (hi_c - lo_c) + b * (np.sin(hi_c) - np.sin(lo_c)), 0.0)
    kernel *= solid[None, :, None] / step  # column average x texel solid angle / pi
    spectrum = np.conj(np.fft.rfft(kernel, axis=2))
    spectrum.flags.writeable = False
    return spectrum


def _uv_pdf_to_solid_angle(pdf_uv, sin_theta):
    """p(w) = p(u, v) / (2 pi^2 sin(theta)), float64; a sample exactly at a pole has no density."""
    pole = sin_theta <= 1e-12
    return np.asarray(pdf_uv, dtype=np.float64) / (2.0 * np.pi * np.pi * np.where(pole, np.inf, sin_theta))


def _sin_theta(directions):
    """sin(theta) of unit directions (..., 3): the length of their (x, z) part (accurate at
    both poles, in the directions' precision)."""
    d = np.asarray(directions)
    x, z = d[..., 0], d[..., 2]
    return np.sqrt(x * x + z * z)


def _channel_mean(radiance: np.ndarray) -> np.ndarray:
    """(H, W) the mean of the three channels: radiance.mean(axis=2) to the bit (the same
    float32 sum, then the division), 10x faster."""
    return (radiance[..., 0] + radiance[..., 1] + radiance[..., 2]) / radiance.dtype.type(3)


def _top_energy_fraction(energy, share: float) -> float:
    """Fraction of the total energy held by the brightest `share` of texels (at least one).
    Only the lit texels are partitioned: a sun split from its sky (split_sun) is all zeros but
    for its few texels, on which numpy's partition took 0.16 s instead of 0.01."""
    total = energy.sum()
    if total <= 0:
        return 0.0
    count = max(1, int(round(share * energy.size)))
    lit = energy[energy > 0]
    if lit.size <= count:
        return 1.0
    top = np.partition(lit, lit.size - count)[lit.size - count:]
    return float(top.sum() / total)
