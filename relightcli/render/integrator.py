"""Monte Carlo environment lighting of what the camera sees: mean, standard error, cost.

A *pass* gives every active pixel one sample of its estimator (for MIS, one environment and
one cosine direction: two shadow rays). Passes run in rounds, each round one vectorised batch;
after a round, pixels whose relative standard error reached the target stop (adaptive), and a
time budget stops everything. Pixels outside the mask trace nothing.

Samples: "sobol" (default) is randomised QMC: one scrambled Sobol sequence shared by all
pixels, each pixel running RQMC_GROUPS copies of it under independent random Cranley-Patterson
shifts (pass k uses point k // R of copy k % R). The copies' means are independent and
unbiased, so their spread gives an honest standard error (the spread of single Sobol passes
would overstate it: the points are better spread than independent ones). "independent"
draws i.i.d. uniforms and estimates the standard error from the pass values.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from relightcli.errors import UsageError
from relightcli.render.camera import PixelGeometry
from relightcli.render.environment import EnvironmentLight, TabulatedSampling
from relightcli.render.estimators import (
    BOUNCE_DIMENSIONS,
    DIMENSIONS,
    RAYS_PER_SAMPLE,
    direct_lighting,
    indirect_lighting,
    lifted_origins,
)
from relightcli.render.parallel import ForkedPasses, pass_statistics
from relightcli.render.scene import Scene
from relightcli.render.sobol import sobol_points

STRATEGIES = ("mis", "env", "cosine", "uniform")
# Independent randomisations of the Sobol sequence per pixel (standard error from R means)
RQMC_GROUPS = 4
SAMPLERS = ("sobol", "independent")
# Rays per vectorised round, shared by the processes (bounds memory: ~300 bytes per ray in flight)
ROUND_RAYS = 1 << 19
# A render forks its workers (parallel.ForkedPasses) only when it may take this many samples
# (pixels x spp, the cap when adaptive): forking and ending them costs ~0.05-0.1 s, more than
# a smaller render gains. The pipeline's renders at 512 (2k-32k pixels, adaptive, cap 32) took
# as long or longer on 2 workers as on 1; 64 spp on the bench's 512 x 512 body scaled 1.6-1.9x
FORK_MIN_SAMPLES = 2_000_000
# Share of the energy in the brightest 0.1% of texels from which the sun is sampled apart
SUN_SPLIT_FRACTION = 0.1
# Pixels darker than this share of the median count as converged at this absolute error
DARK_FLOOR = 0.01
# Share of a time budget kept for assembling the result after the last round
FINISH_SHARE = 0.05
# Sampling decisions floor each pixel's error at POOL_FLOOR x the RMS error of its
# POOL_SIZE x POOL_SIZE neighbourhood: a pixel's own estimate (RQMC_GROUPS group means, 3
# degrees of freedom) is noisy, and with the control variate a pixel whose few samples missed
# a rare occluder reports zero error; neighbours share their occluders. Measured (hard sun,
# 2% target): true / reported median error 1.9% / 0.6% without the floor, 1.35% / 1.5% with
# it; the full RMS as the floor (1.0% / 1.4%) costs 50% more samples.
POOL_SIZE = 5
POOL_FLOOR = 0.5
# Under a time budget alone, pixels whose pooled error is below this share of the median
# stop early (unoccluded pixels are exact with the control variate): the rest get their passes
NEGLIGIBLE_SHARE = 0.25
# Environment samples drawn ahead (environment.TabulatedSampling), once per render: a sample
# then costs a gather, not ~170-220 ns of cdf search and direction. The table has one entry
# per SAMPLE_TABLE_SHARE samples the render may draw (pixels x spp; a power of two of rows,
# at most SAMPLE_TABLE_MAX_ROWS, none below SAMPLE_TABLE_MIN_ROWS): drawing it costs at most an
# eighth of drawing every sample. Its cells are 1 / rows of the first uniform (which runs through
# the map's cells in row-major order: at 16384 rows 2 sky cells of a 1k map) by 1 /
# SAMPLE_TABLE_COLUMNS of the second. At 1024 spp the error stays as without a table, where
# 256 x 256 cells (each spanning a row of the map) raised it 1.7x. 64 spp at 512: 48-54% ->
# 57-59% of raw Embree's ray rate under a hard sun, 47-51% -> 53-60% overcast
# (bench_integrator.py --throughput, alternated runs)
SAMPLE_TABLE_SHARE = 8
SAMPLE_TABLE_COLUMNS = 4
SAMPLE_TABLE_MAX_ROWS = 16384
SAMPLE_TABLE_MIN_ROWS = 256


@dataclass
class ShadingResult:
    """mean, stderr: (H, W, 3) float32 linear radiance (shading units), zero outside mask;
    mask (H, W) bool; passes (H, W) int32 samples per pixel; rays: rays traced here (the
    camera's primary rays are not included); seconds: wall time; strategy: the strategy the plan ran."""

    mean: np.ndarray
    stderr: np.ndarray
    mask: np.ndarray
    passes: np.ndarray
    rays: int
    seconds: float
    strategy: str

    def relative_error(self) -> np.ndarray:
        """(H, W) float32 stderr / mean on the channel average; 0 where both are 0."""
        return _relative(self.mean.mean(axis=2), self.stderr.mean(axis=2), 0.0)

    def median_relative_error(self) -> float:
        """Median over the mask of `relative_error` (0 for an empty mask)."""
        rel = self.relative_error()[self.mask]
        return float(np.median(rel)) if rel.size else 0.0


@dataclass(frozen=True)
class LightingPlan:
    """What a render samples: `terms`, pairs (light, strategy) whose estimates add up to the
    shading under `light` (the whole environment, used by the second bounce)."""

    name: str
    light: EnvironmentLight
    terms: tuple

    @property
    def dims(self) -> int:
        return sum(DIMENSIONS[strategy] for _, strategy in self.terms)

    @property
    def rays_per_pass(self) -> int:
        return sum(RAYS_PER_SAMPLE[strategy] for _, strategy in self.terms)


def plan_lighting(light: EnvironmentLight, requested: str, control_variate: bool = True) -> LightingPlan:
    """What to run. "none" for a black map. "mis" is planned: cosine sampling under a constant
    map (perfect importance sampling), environment sampling when one sun disc holds the
    energy (cosine samples would almost never find it), and when a sun holds a good share
    of it, the sun sampled on its own plus MIS on the rest ("sun+mis"), so that choosing
    between sun and sky adds no variance. With control_variate, the MIS term estimates only
    what occluders take away from the tabulated unoccluded shading ("mis-cv", see
    `direct_lighting`): exact where nothing is in the way. The MIS term samples the map over
    cells of texels (EnvironmentLight.coarse_sampling, the sky of split_sun): a small table
    its random lookups find in cache; on eight maps (studios, a cellar, an arena's spots, sun,
    overcast, night) the error at 32 samples per pixel was within -3% / +0.6% of per-texel
    sampling. Other strategies run as asked."""
    if requested not in STRATEGIES:
        raise UsageError(f"unknown strategy {requested!r}", fix=f"use one of {', '.join(STRATEGIES)}")
    if light.is_black:
        return LightingPlan("none", light, ())
    if requested != "mis":
        return LightingPlan(requested, light, ((light, requested),))
    if light.is_constant:
        return LightingPlan("cosine", light, ((light, "cosine"),))
    if light.is_sun_only:
        return LightingPlan("env", light, ((light, "env"),))
    mis = "mis-cv" if control_variate else "mis"
    if light.sun_fraction >= SUN_SPLIT_FRACTION:
        sun, sky = light.sun_and_sky()
        return LightingPlan(f"sun+{mis}", light, ((sun, "env"), (sky, mis)))
    return LightingPlan(mis, light, ((light.coarse_sampling(), mis),))


def shade_environment(scene: Scene, geometry: PixelGeometry, light: EnvironmentLight, *,
                      spp: int = 64, target_error: float | None = None,
                      time_budget: float | None = None, strategy: str = "mis",
                      bounces: int = 1, albedo=1.0, sampler: str = "sobol", seed: int = 0,
                      min_spp: int = 16, max_distance: float | None = None,
                      workers: int = 1, control_variate: bool = True, lift: float = 0.0) -> ShadingResult:
    """Shading (DESIGN.md units) of every masked pixel under `light`.

    spp: passes per pixel, or the cap when target_error / time_budget are given (rounded up
    to a multiple of RQMC_GROUPS for "sobol"; so is min_spp, the first adaptive round).
    target_error: stop a pixel when stderr / mean (channel average) <= this.
    time_budget: seconds; rounds stop when the next would not fit, and what is left goes to
    the pixels with the largest relative error.
    bounces: 1 (direct) or 2 (plus one diffuse interreflection with `albedo`, a float or an
    (H, W, 3) image aligned with the camera). max_distance: occluders farther than this
    (local units) are ignored. workers: processes sampling in parallel (forked per render;
    worth it from about a second of work). control_variate: see `plan_lighting` (off only
    to measure what it brings). lift: shadow rays leave from points lifted off the triangles
    toward smoother shading normals (estimators.lifted_origins; 0: from the triangles).
    """
    start = time.perf_counter()
    _check_options(spp, target_error, time_budget, bounces, sampler, min_spp)
    plan = plan_lighting(light, strategy, control_variate)
    height, width = geometry.mask.shape
    pixels = np.flatnonzero(geometry.mask.ravel())
    groups = RQMC_GROUPS if sampler == "sobol" else 1
    if time_budget is not None and target_error is None:
        min_spp = max(2, groups)  # a small first round measures the cost of a pass
    if sampler == "sobol":
        spp, min_spp = _round_up(spp, groups), _round_up(min_spp, groups)
    state = _State(pixels.size, groups)
    if plan.terms and pixels.size:
        run = _Run(scene, geometry, plan, pixels, bounces, albedo, max_distance,
                   sampler, seed, spp, lift)
        rays_before = scene.rays_traced
        _sample_rounds(run, state, spp, target_error, time_budget, min_spp, start, workers)
        rays = scene.rays_traced - rays_before
    else:
        rays = 0
    mean, stderr = state.estimates()
    # A control variate can undershoot a dim, mostly occluded pixel at low sample counts;
    # shading is never negative, so clamping there only moves the estimate closer
    mean = np.maximum(mean, 0.0)
    out_mean = np.zeros((height * width, 3), np.float32)
    out_err = np.zeros((height * width, 3), np.float32)
    out_passes = np.zeros(height * width, np.int32)
    out_mean[pixels], out_err[pixels], out_passes[pixels] = mean, stderr, state.count
    return ShadingResult(mean=out_mean.reshape(height, width, 3),
                         stderr=out_err.reshape(height, width, 3), mask=geometry.mask.copy(),
                         passes=out_passes.reshape(height, width), rays=int(rays),
                         seconds=time.perf_counter() - start, strategy=plan.name)


def ambient_occlusion(scene: Scene, geometry: PixelGeometry, *, spp: int = 64,
                      max_distance: float | None = None, sampler: str = "sobol",
                      seed: int = 0, target_error: float | None = None,
                      workers: int = 1) -> ShadingResult:
    """Unoccluded fraction of the cosine-weighted hemisphere, in [0, 1], as the shading under
    a constant white environment (cosine sampling; occluders beyond max_distance ignored).
    The result's channels are equal."""
    white = EnvironmentLight(np.ones((1, 2, 3), np.float32))
    return shade_environment(scene, geometry, white, spp=spp, target_error=target_error,
                             strategy="cosine", sampler=sampler, seed=seed,
                             max_distance=max_distance, workers=workers)


# ---------------------------------------------------------------------------- internals
class _State:
    """Running per-pixel sums (float64): pass values per randomisation group, their squares,
    pass counts. groups == 1: i.i.d. passes, the standard error comes from the squares;
    groups == R > 1: pass k belongs to group k % R, the error comes from the R group means."""

    def __init__(self, n, groups):
        self.groups = groups
        self.group_total = np.zeros((n, groups, 3))
        self.squares = np.zeros((n, 3))
        self.count = np.zeros(n, np.int64)

    def add(self, rows, statistics, passes):
        """Add `pass_statistics` of `passes` passes of the pixels `rows`."""
        group_sums, square_sums = statistics
        if rows.size == self.count.size:  # every pixel (rows are sorted): no gather / scatter
            rows = slice(None)
        self.group_total[rows] += group_sums
        if square_sums is not None:
            self.squares[rows] += square_sums
        self.count[rows] += passes

    def estimates(self):
        """(mean, stderr), each (n, 3) float32."""
        n = np.maximum(self.count, 1)[:, None].astype(np.float64)
        mean = self.group_total.sum(axis=1) / n
        if self.groups == 1:
            variance = np.maximum(self.squares / n - mean ** 2, 0.0) / np.maximum(n - 1, 1)
        else:  # every group holds count / r passes (passes come in multiples of r)
            r = self.groups
            deviation = self.group_total / (n[:, :, None] / r) - mean[:, None, :]
            variance = np.einsum("ngc,ngc->nc", deviation, deviation) / (r * (r - 1))
        return mean.astype(np.float32), np.sqrt(variance).astype(np.float32)

    def relative_error(self):
        """(n,) stderr / mean on the channel average; pixels darker than DARK_FLOOR x the
        median are measured against that floor (they cannot hold up the render)."""
        mean, stderr = self.estimates()
        lum = mean.mean(axis=1)
        floor = DARK_FLOOR * np.median(lum) if lum.size else 0.0
        if floor > 0:
            return stderr.mean(axis=1) / np.maximum(lum, floor)
        return _relative(lum, stderr.mean(axis=1), 0.0)


class _Run:
    """Everything one render needs to produce pass values for any set of pixels."""

    def __init__(self, scene, geometry, plan, pixels, bounces, albedo, max_distance,
                 sampler, seed, spp, lift):
        self.scene, self.plan = scene, plan
        self.bounces, self.max_distance = bounces, max_distance
        # float32 per pixel, as the tracer takes them (the pass loop gathers them every round)
        points = geometry.position.reshape(-1, 3)[pixels].astype(np.float64)
        normals = geometry.normal.reshape(-1, 3)[pixels].astype(np.float64)
        geometric = geometry.geometric_normal.reshape(-1, 3)[pixels].astype(np.float64)
        origins, horizon = lifted_origins(scene, points, normals, geometric, lift)
        self.origins = origins.astype(np.float32)
        self.normals, self.horizon = normals.astype(np.float32), horizon.astype(np.float32)
        self.albedo_at = _albedo_lookup(albedo, geometry, scene)
        # Tabulated unoccluded shading for the control-variate terms, once per pixel
        self.unoccluded = [light.irradiance(self.normals) if strategy == "mis-cv" else None
                           for light, strategy in plan.terms]
        shape = _table_shape(pixels.size * spp)
        if shape is not None:
            self.plan = plan = _tabulated(plan, shape, seed)
        self.sampler, self.seed, self.pixel_count = sampler, seed, pixels.size
        # The mask's bounding box, grown by the pooling radius: where stopping_error filters
        rows, cols = np.divmod(pixels, geometry.mask.shape[1])
        if pixels.size:
            r0, c0 = rows.min() - POOL_SIZE // 2, cols.min() - POOL_SIZE // 2
            rows, cols = rows - r0, cols - c0
        self.pool_shape = (int(rows.max(initial=0)) + POOL_SIZE, int(cols.max(initial=0)) + POOL_SIZE)
        self.pool_index = rows * self.pool_shape[1] + cols
        # Separate streams for direct light and the bounce: adding the bounce leaves the
        # direct-light samples as they were
        self.streams = {"direct": plan.dims, "bounce": BOUNCE_DIMENSIONS if bounces == 2 else 0}
        if sampler == "sobol":
            points = max(2, -(-spp // RQMC_GROUPS))
            self.sobol, self.shift = {}, {}
            for index, (name, dims) in enumerate(self.streams.items()):
                if dims:
                    self.sobol[name] = sobol_points(dims, int(np.ceil(np.log2(points))),
                                                    np.random.default_rng([seed, 1, index]))
                    self.shift[name] = np.random.default_rng([seed, 2, index]).random(
                        (RQMC_GROUPS, pixels.size, dims))

    def uniforms(self, stream, first_pass, passes, rows):
        """(passes * len(rows), dims) float64 in [0, 1), pass-major: deterministic in
        (seed, stream, pass, pixel)."""
        dims = self.streams[stream]
        if self.sampler == "sobol":
            every = rows.size == self.pixel_count
            shifts = [group if every else np.take(group, rows, axis=0) for group in self.shift[stream]]
            u = np.empty((passes, rows.size, dims))
            for i, k in enumerate(range(first_pass, first_pass + passes)):
                np.add(self.sobol[stream][k // RQMC_GROUPS], shifts[k % RQMC_GROUPS], out=u[i])
            u -= u >= 1.0  # Cranley-Patterson rotation: (point + shift) mod 1
            return u.reshape(-1, dims)
        out = np.empty((passes, rows.size, dims))
        index = list(self.streams).index(stream)
        for k in range(passes):
            rng = np.random.default_rng([self.seed, 3, index, first_pass + k])
            out[k] = rng.random((self.pixel_count, dims))[rows]
        return out.reshape(-1, dims)

    def stopping_error(self, state) -> np.ndarray:
        """(n,) the error sampling decisions use: each pixel's relative error, at least
        POOL_FLOOR x the RMS of its neighbourhood's (POOL_SIZE, masked pixels only)."""
        from scipy.ndimage import uniform_filter

        own = np.minimum(state.relative_error(), 1e3)  # finite: a squared inf would spread
        squares, weights = np.zeros(self.pool_shape), np.zeros(self.pool_shape)
        squares.flat[self.pool_index], weights.flat[self.pool_index] = own ** 2, 1.0
        pooled = (uniform_filter(squares, POOL_SIZE, mode="constant").flat[self.pool_index]
                  / uniform_filter(weights, POOL_SIZE, mode="constant").flat[self.pool_index])
        pooled = np.sqrt(np.maximum(pooled, 0.0))  # the filter's round-off can dip below 0
        return np.maximum(own, POOL_FLOOR * pooled)

    def repeat(self, per_pixel, rows, passes):
        """The rows `rows` of a per-pixel array, once per pass, pass-major: one gather and
        copies of it (gathering every copy cost ~3x as much)."""
        chosen = per_pixel if rows.size == self.pixel_count else np.take(per_pixel, rows, axis=0)
        return np.tile(chosen, (passes, 1))

    def values(self, first_pass, passes, rows):
        """(passes, len(rows), 3) float64 pass values for the pixels `rows`."""
        u = self.uniforms("direct", first_pass, passes, rows)
        p, n, g = (self.repeat(a, rows, passes) for a in (self.origins, self.normals, self.horizon))
        value = np.zeros((passes * rows.size, 3))
        d = 0
        for (light, strategy), unoccluded in zip(self.plan.terms, self.unoccluded):
            k = DIMENSIONS[strategy]
            value += direct_lighting(self.scene, light, p, n, g, u[:, d:d + k], strategy,
                                     self.max_distance,
                                     None if unoccluded is None else self.repeat(unoccluded, rows, passes))
            d += k
        if self.bounces == 2:
            value += indirect_lighting(self.scene, self.plan.light, p, n, g,
                                       self.uniforms("bounce", first_pass, passes, rows),
                                       self.albedo_at)
        return value.reshape(passes, rows.size, 3)


def _table_shape(samples: int) -> tuple[int, int] | None:
    """The (rows, columns) of the sample tables of a render that may draw `samples` samples
    a term, or None for none (see SAMPLE_TABLE_SHARE)."""
    rows = int(samples) // (SAMPLE_TABLE_SHARE * SAMPLE_TABLE_COLUMNS)
    if rows < SAMPLE_TABLE_MIN_ROWS:
        return None
    return min(SAMPLE_TABLE_MAX_ROWS, 1 << (rows.bit_length() - 1)), SAMPLE_TABLE_COLUMNS


def _tabulated(plan: LightingPlan, shape: tuple, seed: int) -> LightingPlan:
    """The plan with the environment-sampled terms' samples drawn ahead in tables of `shape`,
    once per render (deterministic in the seed; forked workers inherit the tables)."""
    terms = tuple((TabulatedSampling(light, shape, np.random.default_rng([seed, 4, index]))
                   if strategy in ("mis", "mis-cv", "env") else light, strategy)
                  for index, (light, strategy) in enumerate(plan.terms))
    return LightingPlan(plan.name, plan.light, terms)


def _sample_rounds(run, state, spp, target_error, time_budget, min_spp, start, workers):
    """Run passes in rounds until every pixel is done, spp is reached or time is up."""
    if workers > 1 and run.pixel_count * spp >= FORK_MIN_SAMPLES:
        with ForkedPasses(run, workers) as pool:
            _rounds(pool.statistics, run, state, spp, target_error, time_budget, min_spp, start)
    else:
        def statistics(first_pass, passes, rows, groups):
            return pass_statistics(run.values(first_pass, passes, rows), first_pass, groups)

        _rounds(statistics, run, state, spp, target_error, time_budget, min_spp, start)


def _rounds(statistics, run, state, spp, target_error, time_budget, min_spp, start):
    """The sampling loop; statistics(first_pass, passes, rows, groups) evaluates a round.
    Adaptive decisions use `run.stopping_error` (pooled over neighbours). The rounds, and so
    which pixel gets which passes, do not depend on how many processes share them: without a
    time budget the result is the same for any worker count."""
    adaptive = target_error is not None or time_budget is not None
    active = np.arange(state.count.size)
    done_passes = 0
    seconds_per_pass_pixel = error = None
    rays_per_pass = run.plan.rays_per_pass + (2 if run.bounces == 2 else 0)
    while active.size and done_passes < spp:
        passes = _round_passes(done_passes, spp, active.size, rays_per_pass, adaptive, min_spp,
                               None if error is None else error[active], target_error)
        passes = min(_round_up(passes, state.groups), spp - done_passes)
        if time_budget is not None and seconds_per_pass_pixel is not None:
            left = (1.0 - FINISH_SHARE) * time_budget - (time.perf_counter() - start)
            affordable = int(left / (seconds_per_pass_pixel * active.size))
            passes = min(passes, affordable - affordable % state.groups)
            if passes < 1:
                # What is left buys one more group of passes for the pixels with most error
                count = int(0.9 * left / (seconds_per_pass_pixel * state.groups))  # margin: a partial round costs more per pixel
                if count >= 1:
                    worst = active[np.argsort(-error[active], kind="stable")[:count]]
                    worst.sort()
                    state.add(worst, statistics(done_passes, state.groups, worst, state.groups),
                              state.groups)
                break
        tick = time.perf_counter()
        state.add(active, statistics(done_passes, passes, active, state.groups), passes)
        seconds_per_pass_pixel = (time.perf_counter() - tick) / (passes * active.size)
        done_passes += passes
        if adaptive:
            error = run.stopping_error(state)
        if target_error is not None:
            active = active[error[active] > target_error]
        elif time_budget is not None:
            active = active[error[active] >= NEGLIGIBLE_SHARE * np.median(error[active])]


def _round_passes(done, spp, n_active, rays_per_pass, adaptive, min_spp, error, target_error):
    """Passes in the next round: a first round of min_spp when adaptive, then about as many as
    the median active pixel still needs (`error`: the active pixels' stopping errors), between
    half and all of what is done so far (so the rounds, each with a fixed cost, grow
    geometrically), within spp and the ray budget."""
    cap = max(1, ROUND_RAYS // (rays_per_pass * n_active))
    if not adaptive:
        return int(min(spp - done, cap))
    if done == 0:
        return int(min(min_spp, spp, cap))
    if target_error is None:
        return int(min(spp - done, cap, done))
    need = np.median(done * ((error / target_error) ** 2 - 1.0))
    return int(min(max(np.ceil(need), done // 2, 1), done, spp - done, cap))


def _round_up(value, multiple):
    return int(-(-int(value) // multiple) * multiple)


def _albedo_lookup(albedo, geometry: PixelGeometry, scene: Scene):
    """A function local points (N, 3) -> albedo (N, 3) float64: a constant, or the camera-
    aligned image sampled at the pixel a point projects to (orthographic along -Z)."""
    if np.ndim(albedo) == 0:
        value = float(albedo)
        return lambda q: np.full((q.shape[0], 3), value)
    image = np.asarray(albedo, dtype=np.float64)
    height, width = geometry.mask.shape
    if image.shape != (height, width, 3):
        raise UsageError(f"albedo image must be {(height, width, 3)}, got {image.shape}")
    x0, x1, y0, y1 = geometry.rect

    def lookup(q):
        world = scene.to_world(q)
        col = np.clip(((world[:, 0] - x0) / (x1 - x0) * width).astype(np.int64), 0, width - 1)
        row = np.clip(((y1 - world[:, 1]) / (y1 - y0) * height).astype(np.int64), 0, height - 1)
        return image[row, col]

    return lookup


def _relative(mean, stderr, floor):
    mean = np.asarray(mean, dtype=np.float64)
    safe = np.where(mean > floor, mean, 1.0)
    return np.where(mean > floor, stderr / safe, np.where(stderr > 0, np.inf, 0.0)).astype(np.float32)


def _check_options(spp, target_error, time_budget, bounces, sampler, min_spp):
    if int(spp) < 1:
        raise UsageError(f"spp must be >= 1, got {spp}")
    if target_error is not None and not target_error > 0:
        raise UsageError(f"target error must be > 0, got {target_error}")
    if time_budget is not None and not time_budget > 0:
        raise UsageError(f"time budget must be > 0 seconds, got {time_budget}")
    if bounces not in (1, 2):
        raise UsageError(f"bounces must be 1 or 2, got {bounces}")
    if sampler not in SAMPLERS:
        raise UsageError(f"unknown sampler {sampler!r}", fix=f"use one of {', '.join(SAMPLERS)}")
    if int(min_spp) < 2:
        raise UsageError(f"min_spp must be >= 2 (a standard error needs two passes), got {min_spp}")
