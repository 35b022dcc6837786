"""Shading under the target environment: the reconstruction and the fitted bodies ray-traced by
our Monte Carlo integrator (hard cast shadows, a measured error), or the SH baselines."""

from __future__ import annotations

import numpy as np

from relightcli import compose
from relightcli.compose import bounding_box, fill_smooth, fill_uncovered
from relightcli.layers import DEFAULT_SPP_CAP, DEFAULT_TARGET_ERROR, SHADOW_STEP
from relightcli.stages.body import body_shading_pixels
from relightcli.stages.frame import Frame, Models, person_support


def build_scene(frame: Frame, options) -> None:
    """The Embree scene and the camera's primary hits: built once per photo, whatever the
    number of lightings (a turntable re-lights the same scene).

    The hits are shaded with the normal net's normals where they face the mesh's side: the
    mesh (from the depth maps, smoothed) decides what is occluded, the net's normals the
    cosine term. Measured on the 20 eval scenes (true mask, no refinement): shading 16.3 ->
    17.0 dB, relit 14.7 -> 15.0 dB against the mesh's own normals."""
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.scene import Scene

    # One tracing process: the camera's rays take ~50 ms on one core, and the integrator
    # samples on its own forked workers; a tracing pool would spawn a process per photo
    # Area-weighted vertex normals of our own (trimesh's take ~4x longer at 512)
    frame.scene = Scene(frame.mesh.vertices, frame.mesh.faces, threads=1)
    # Only the person's pixels: the shading is multiplied by the crop mask, so nothing else is shaded
    hits = render_pixel_geometry(frame.scene, compose.CROP_RECT, (options.resolution,) * 2,
                                 where=frame.crop_mask > 0)
    frame.hits = hits.with_shading_normals(frame.geometry.front_normal, frame.crop_mask > 0.5)
    frame.notes.setdefault("scene_builds", 0)
    frame.notes["scene_builds"] += 1


def ensure_scenes(frame: Frame, options, models: Models) -> None:
    """Build the reconstruction's scene once per photo (the bodies' is the body_maps stage's)."""
    if frame.scene is None:
        build_scene(frame, options)


# The fitted bodies' share of the coarse shading where a fit converged (stage_raytrace): 0.5
# chosen with the image-alone geometry net, 0.3 once the prior net shaped the reconstruction
# (validation, true mask, shading / relit: 0.5 19.46 / 16.52, 0.3 19.65 / 16.54, 0 18.83 / 16.13;
# python bench/bench_geometry_prior.py data/evalval512 --use-gt-mask --body-weight W), 0.2 once
# the reconstruction's normals took the outline's (relightcli.geometry.silhouette): relit /
# albedo / shading, 150 validation scenes at 256 17.917 / 18.292 / 19.961 -> 17.952 / 18.303 /
# 20.032 (relit better in 89 of 150), 20 at 512 17.967 / 17.211 / 21.469 -> 17.976 / 17.213 /
# 21.623 (0.4: 17.924 / 17.199 / 21.209)
BODY_SHADING_WEIGHT = 0.2


def body_weight(frame: Frame) -> np.ndarray:
    """(R, R) float32: the fitted bodies' share of the traced shading per crop pixel."""
    return np.float32(BODY_SHADING_WEIGHT) * body_shading_pixels(frame)


def stage_raytrace(frame: Frame, options, models: Models) -> None:
    """Coarse shading under the target environment, pixel-aligned with the crop: the
    reconstructed mesh ray-traced (build_scene), averaged (the bodies' share
    BODY_SHADING_WEIGHT) with the fitted naked bodies ray-traced (stage_body_maps) over the
    people whose body fit converged (the target error is the blend's, shared by the two
    renders in proportion to their weights: blend_targets). Person pixels a mesh does not
    cover (limbs thinner than two pixels on the reconstruction; clothes and hair around the naked body; the soft edge of the
    mask, where the smoothed mesh has shrunk; a depth step between two bodies) take the shading
    of the nearest covered pixel within 2 px, further in a smooth fill (compose.fill_smooth).

    Measured (issue 18): `relight eval DATA --method raytrace-norefine [--use-gt-mask]`, relit /
    albedo / shading PSNR; the weight chosen on data/evalval512 among 0, 0.3, 0.5, 0.7 and 1
    (shading 17.69, 19.25, 19.49, 19.19, 17.96 dB with the true mask):
    | scenes, mask             | reconstruction        | bodies alone          | mean (shipped)        |
    | val, true mask           | 15.92 / 16.19 / 17.69 | 15.89 / 16.19 / 17.96 | 16.57 / 16.19 / 19.49 |
    | val, own mask (17 found) | 15.14 / 16.06 / 15.10 | 15.28 / 16.06 / 15.71 | 15.80 / 16.06 / 16.55 |
    | test, true mask          | 17.81 / 18.70 / 17.40 | 17.37 / 18.70 / 17.17 | 18.06 / 18.70 / 18.62 |
    | test, own mask           | 17.19 / 18.45 / 15.85 | 16.88 / 18.45 / 15.93 | 17.48 / 18.45 / 16.89 |
    With the refinement net after it (`--method raytrace`, val, true mask): relit / shading
    16.68 / 19.63 against 15.97 / 17.92. One scene of reconstruction and bodies (primary hits
    on whichever is in front: val shading 17.57) or the body as a shadow caster behind the
    reconstruction's hits (15.87: it pokes through the clothes) lost: the two surfaces' errors
    are unlike, and the mean of their shadings beats either. So did one mesh with every surface
    (issue 18 step 4, bench/bench_fusion.py, true mask, shading val / test against 19.49 / 18.62
    shipped): ECON's screened Poisson (pymeshlab, depth 8) of the reconstruction and the bodies'
    parts neither camera sees 17.55 / 17.37 (3-6 s a photo, watertight 10/16 and 19/20), the
    union of both solids as one depth mesh 17.52 / 17.24, and either in the mean in place of the
    reconstruction 19.37 / 18.52 and 19.20 / 18.33; the mesh's cover of the person (96%, the
    rest filled from the nearest pixel) is not what limits it: smoothing it in depth only (98%)
    scored 19.46 on val. What Poisson did win, with the predicted mask (shading val 16.55 ->
    17.05, test 16.89 -> 17.43), came from covering the mask's soft edge (0 < crop mask <= 0.5,
    multiplied in, not dropped), which was left black where the smoothed meshes shrink from it;
    filling it from the nearest covered pixel as the rest gives, by `relight eval`, relit /
    albedo / shading: val true mask 16.58 / 16.19 / 19.56 (was 16.57 / 16.19 / 19.49), val own
    mask 16.15 / 16.06 / 17.88 (15.80 / 16.06 / 16.55), test true mask 18.05 / 18.70 / 18.67
    (18.06 / 18.70 / 18.62), test own mask 17.81 / 18.45 / 17.82 (17.48 / 18.45 / 16.89)."""
    ensure_scenes(frame, options, models)
    frame.coarse_shading, frame.notes["raytrace"] = trace_shading(frame, models.light(frame.env), options)
    frame.shading = frame.coarse_shading * person_support(frame)


def _trace_note(result) -> dict:
    return {"spp_mean": float(result.passes[result.mask].mean()) if result.mask.any() else 0.0,
            "rays": result.rays, "seconds": round(result.seconds, 4), "strategy": result.strategy,
            "rel_error": result.median_relative_error(),
            "mrays_per_s": result.rays / max(result.seconds, 1e-9) / 1e6}


# Shadow rays leave the meshes lifted toward the shading normals (render.estimators.
# lifted_origins, in edge lengths): the reconstruction is shaded with the nets' normals, the
# bodies with their smooth vertex normals, and traced from the triangles themselves a grazing
# sun's terminator came out as a staircase of facets (2-3 px steps across a face).
SHADOW_LIFT = 1.0
# The traced visibility is filtered with the integrator's own error estimate (render.denoise,
# adaptive_wiener) in windows of 2 r + 1 pixels; 0: not filtered
SHADING_FILTER_RADIUS = 1


def trace_shading(frame: Frame, light, options, step: int | None = None) -> tuple[np.ndarray, dict]:
    """(shading (R, R, 3), note): the reconstruction ray-traced under `light` (an
    EnvironmentLight), blended with the fitted bodies' (body_weight) where a fit converged;
    person pixels a mesh does not cover, the mask's soft edge included, are filled from the
    covered ones (stage_raytrace). `--shadows half` traces every second pixel's rays
    (traced); step: another pixel step for the rays than `--shadows` gives."""
    spp, target = sampling_effort(options)
    wanted = frame.crop_mask > 0
    blended = frame.body_scene is not None
    own_target, body_target = blend_targets(target, BODY_SHADING_WEIGHT, body_shading_pixels(frame).all()) \
        if blended and target is not None else (target, target)
    step = SHADOW_STEP[options.shadows] if step is None else step
    own, result = traced(frame.scene, frame.hits, light, spp, own_target, options.seed, options.threads,
                         wanted, step)
    shading, note = np.ascontiguousarray(own[..., :3]), {**_trace_note(result), "shadow_step": step,
                                                         "shadow_lift": SHADOW_LIFT}
    if not blended:
        note["body"] = "no converged body fit: the reconstruction's shading alone"
        return shading, note
    body_filled, body = traced(frame.body_scene, frame.body_hits, light, spp, body_target, options.seed,
                               options.threads, wanted, step)
    weight = body_weight(frame)[..., None]
    note["body"] = {"weight": BODY_SHADING_WEIGHT, **_trace_note(body)}
    mean = (1.0 - weight) * shading + weight * body_filled[..., :3]
    # The blend's own error (the two renders are independent): what the target is met on;
    # the reconstruction's beside it over the same full-resolution pixels (its note's
    # rel_error is over the coarse grid's, where more pixels are exact than after upsampling)
    stderr = np.hypot((1.0 - weight) * own[..., 3:], weight * body_filled[..., 3:])
    pixels = wanted & frame.hits.mask
    note["reconstruction_rel_error"] = median_relative_error(shading, own[..., 3:], pixels)
    note["rel_error"] = median_relative_error(mean, stderr, pixels)
    return mean, note


def traced(scene, hits, light, spp, target, seed, threads, wanted, step) -> tuple[np.ndarray, object]:
    """(mean and standard error (R, R, 6) float32 over the pixels `wanted`, the integrator's
    ShadingResult) of the camera's hits on a scene under `light` (an EnvironmentLight).

    step 1: every hit is ray-traced. step > 1: only every step-th pixel's in both directions
    (a 1 / step^2 share of the rays), and what the rays found there, the visibility V = traced
    / unoccluded shading (cast shadows and occlusion: 1 where nothing blocks the light), is
    interpolated to every pixel and multiplied by that pixel's own unoccluded shading, exact
    from the light's irradiance table (the integrator's control variate) at its own normal: the
    normals' detail stays at full resolution, only shadows and occlusion come at the coarse
    grid's. The error reported is the coarse render's Monte Carlo error carried the same way.
    Person pixels no hit covers are filled smoothly from the covered ones (fill_smooth).

    Measured at step 2 (`relight eval DATA --use-gt-mask [--shadows full]`, relit / shading
    dB, against step 1): validation 16.81 / 20.43 (16.82 / 20.45), test 18.06 / 19.00 (18.05 /
    19.00); the shading's SSIM 0.756 / 0.658 (0.752 / 0.654). The ray tracing stage at 512
    0.40 s instead of 0.74 s (`python bench/bench_pipeline.py [--shadows full]`). The coarse
    shading itself interpolated, without the ratio, lost 0.2 dB of shading on validation.

    The visibility is filtered before it is used (SHADING_FILTER_RADIUS, at either step):
    render.denoise.adaptive_wiener with the integrator's own per-pixel error, which takes out
    the noise a map of many small lights leaves at the sample cap (dark speckles where a few
    occluded samples drew a bright lamp) and keeps a cast shadow's edge. The returned error is
    the Monte Carlo error before filtering."""
    from relightcli.render.denoise import adaptive_wiener, visibility
    from relightcli.render.integrator import shade_environment

    coarse = hits.subsampled(step)
    result = shade_environment(scene, coarse, light, spp=spp, target_error=target, seed=seed, workers=threads,
                               lift=SHADOW_LIFT)
    seen, error, unoccluded, dark = visibility(result, light, coarse.normal)
    if SHADING_FILTER_RADIUS:
        seen = adaptive_wiener(seen, error, coarse.mask & ~dark.any(axis=-1), SHADING_FILTER_RADIUS)
    if step == 1:
        mean = np.where(dark, result.mean, seen * unoccluded) if SHADING_FILTER_RADIUS else result.mean
        # means and errors filled together: one distance transform per render
        return fill_smooth(np.concatenate([mean, result.stderr], axis=-1), hits.mask, wanted), result
    ratio = fill_uncovered(np.concatenate([seen, error], axis=-1), coarse.mask,
                           np.ones(coarse.mask.shape, bool))
    full = np.zeros(hits.mask.shape + (3,), np.float32)
    full[hits.mask] = light.irradiance(hits.normal[hits.mask])
    # zero where no hit: upsampled over the hits' box only
    box = bounding_box(hits.mask)
    values = np.zeros(hits.mask.shape + (6,), np.float32)
    values[box] = upsample(ratio.astype(np.float32), hits.mask.shape, step, box) * \
        np.concatenate([full[box], full[box]], axis=-1)
    return fill_smooth(values, hits.mask, wanted), result


def upsample(image: np.ndarray, shape: tuple, step: int, box: tuple | None = None) -> np.ndarray:
    """(H, W, C) bilinear from a coarse image (h, w, C) whose pixel (i, j) lies on pixel
    (step i, step j) of the fine one (PixelGeometry.subsampled); held beyond its last row and
    column. box: (rows, columns) slices of the fine image: only that window of it."""
    def axis(fine, coarse):
        at = np.arange(fine.start, fine.stop) / step
        low = np.minimum(at.astype(np.int64), coarse - 1)
        high = np.minimum(low + 1, coarse - 1)
        return low, high, np.clip(at - low, 0.0, 1.0).astype(np.float32)[:, None]

    fine_rows, fine_cols = box or (slice(0, shape[0]), slice(0, shape[1]))
    r0, r1, fr = axis(fine_rows, image.shape[0])
    c0, c1, fc = axis(fine_cols, image.shape[1])
    rows = image[r0] * (1.0 - fr[..., None]) + image[r1] * fr[..., None]
    return rows[:, c0] * (1.0 - fc) + rows[:, c1] * fc


def blend_targets(target: float, weight: float, everywhere: bool) -> tuple[float, float]:
    """Relative-error targets of the reconstruction's and the bodies' renders whose blend
    (1 - weight) * own + weight * body reaches `target` at the least cost: a render's samples
    in proportion to its weight (minimise 1/n_own + 1/n_body at fixed (1 - w)^2 / n_own +
    w^2 / n_body), i.e. target / sqrt(1 - w) and target / sqrt(w). Where a person's fit did not
    converge (not `everywhere`) the reconstruction is shaded alone and keeps the target."""
    own = target / np.sqrt(1.0 - weight) if everywhere and weight < 1.0 else target
    body = target / np.sqrt(weight) if weight > 0.0 else target
    return float(own), float(body)


def median_relative_error(mean: np.ndarray, stderr: np.ndarray, where: np.ndarray) -> float:
    """Median over `where` of stderr / mean on the channel average (0 where the mean is 0)."""
    m, e = mean[where].mean(axis=-1), stderr[where].mean(axis=-1)
    rel = np.where(m > 0, e / np.where(m > 0, m, 1.0), 0.0)
    return float(np.median(rel)) if rel.size else 0.0


def sampling_effort(options) -> tuple[int, float | None]:
    """(spp or cap, target relative error) from --spp / --target-error."""
    if options.spp is not None:
        return options.spp, None
    return DEFAULT_SPP_CAP, options.target_error or DEFAULT_TARGET_ERROR


def stage_sh_shading(frame: Frame, options, models: Models) -> None:
    """RH / SFHR-style baselines: SH-9 or SH-25 irradiance of the target environment at the
    predicted normals (no visibility)."""
    from relightcli.render.sh import project_sh, sh_irradiance_shading

    order = 2 if options.method == "sh9" else 4
    coefficients = project_sh(frame.env, order)
    shading = sh_irradiance_shading(coefficients, frame.normal)
    frame.shading = np.maximum(shading, 0.0) * person_support(frame)
