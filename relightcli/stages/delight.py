"""De-lighting: the input light and the albedo. The de-lighting net's guess, the input light
solved again by inverse rendering on the meshes, and the photo divided by that light's shading."""

from __future__ import annotations

import functools
import time
from dataclasses import replace

import cv2
import numpy as np

from relightcli import compose
from relightcli.compose import fill_uncovered
from relightcli.layers import INPUT_SHADOW_GRID, SHADOW_STEP
from relightcli.stages.body import body_shading_pixels
from relightcli.stages.frame import Frame, Models, net_side, person_support, resample, unit
from relightcli.stages.geometry import MIRROR_AVERAGED, mirror
from relightcli.stages.shading import SHADOW_LIFT, body_weight, ensure_scenes, trace_shading


def stage_delight(frame: Frame, options, models: Models) -> None:
    """De-lighting: the input lighting (16x32) and an albedo. The net gives a light and an
    albedo from [crop, normals]. `--albedo solve` (the default) solves the light again by
    inverse rendering on the mesh (solve_input_light) and divides the crop by the ray-traced
    shading of that light (cast shadows and occlusion leave the albedo with it); `--albedo
    ratio` divides by the SH-9 irradiance of the net's light at the predicted normals; both
    blend into the net's albedo where that shading is too dark to divide by
    (compose.ratio_albedo), take the net's albedo level (one gain) and, on the outline, the
    mean of its albedo and the nearest pixel's inside (compose.anchor_albedo). `--albedo net`
    keeps the net's (the paper's).

    Measured (`relight eval DATA [--albedo ratio]`, relit / albedo PSNR, ratio -> solve): test
    scenes (data/eval512) 18.67 / 19.47 -> 18.82 / 19.74, true mask 19.04 / 19.84 -> 19.28 /
    20.17; 150 validation scenes at 256, true mask, 17.70 / 18.27 -> 18.13 / 18.80; 20 at 512
    16.77 / 16.14 -> 17.38 / 16.94; for ~0.45 s more a photo at 512. Dividing by the traced
    shading of the *true* light scores 19.67 / 19.95 (validation, 512, no refinement): the
    light's shape and level, not the division, is what is left. The input shading is traced
    with the target's effort: capped at 8 samples per pixel it lost 0.04 / 0.09 dB on
    validation for ~25% less time per image. Its rays are traced on a coarser grid instead
    (input_shadow_step): at 512 every fourth pixel scored as every second (validation, true
    mask, relit / albedo 17.800 / 17.190 -> 17.800 / 17.196; every eighth 17.794 / 17.196) with
    a quarter of the rays (~55k instead of ~220k a photo); at 256 every fourth lost 0.007 /
    0.004 dB on the 150 validation scenes, so 256 keeps every second."""
    from relightcli.render.environment import EnvironmentLight
    from relightcli.render.sh import project_sh, sh_irradiance_shading

    result = net_estimate(frame, models.get("delight"), options)
    albedo, frame.light = result.albedo, result.light
    if options.albedo == "solve":
        solved, frame.light = solve_input_light(frame, albedo, options, models)
        start = time.perf_counter()
        input_shading, note = trace_shading(frame, EnvironmentLight(solved), options, input_shadow_step(options))
        input_shading = compose.shading_the_photo_shows(input_shading, frame.crop, frame.crop_mask,
                                                        SHADING_DIP_SIGMA * options.resolution)
        frame.notes["delight"]["input_shading"] = {**{key: note[key] for key in ("shadow_step", "rays", "rel_error")},
                                                   "seconds": round(time.perf_counter() - start, 4)}
    elif options.albedo == "ratio":
        input_shading = sh_irradiance_shading(project_sh(result.light, 2), frame.normal)
    if options.albedo != "net":
        frame.input_shading = input_shading
        ratio = compose.ratio_albedo(frame.crop, input_shading, albedo, frame.crop_mask)
        gain = compose.albedo_gain(ratio, albedo, frame.crop_mask)
        frame.notes.setdefault("delight", {})["albedo_level"] = albedo_level_note(gain)
        albedo = compose.anchor_albedo(ratio, albedo, frame.crop_mask, gain=gain)
    # Outside the mask's 0.5 contour a pixel mixes in the background (the photo there is mostly
    # not the person): it takes the albedo of the nearest pixel inside, so the soft edge, now
    # straight, does not carry the background's colour into the relit person
    inside = frame.crop_mask > 0.5
    albedo = fill_uncovered(albedo, inside, frame.crop_mask > 0) if inside.any() else albedo
    frame.albedo = albedo * person_support(frame)


def net_estimate(frame: Frame, net, options):
    """The de-lighting net's DelightResult on the frame's crop and normals at the side the net
    learned on (the photo and its mirror averaged when "delight" is in MIRROR_AVERAGED), its
    albedo resampled to the working resolution."""
    side = net_side(net, options.resolution)
    image, normal = resample(frame.crop, side), unit(resample(frame.normal, side))
    result = net.predict(image, normal)
    if "delight" in MIRROR_AVERAGED:
        mirrored = net.predict(mirror(image), mirror(normal, (0,)))
        result = replace(result, albedo=0.5 * (result.albedo + mirror(mirrored.albedo)),
                         light=0.5 * (result.light + mirror(mirrored.light)))
    return replace(result, albedo=resample(result.albedo, options.resolution))


# The solved light's shading may dip below its surroundings (a Gaussian of this share of the
# crop's side: 8 px at 512) only as far as the photo does (compose.shading_the_photo_shows)
SHADING_DIP_SIGMA = 1.0 / 64


# The albedo level's error, RMS over the 60 validation people at 512 (true mask, `python
# bench/light_solve.py data/evalval512p60 data/factory512val60 --split val --use-gt-mask`): log2
# of the true albedo's median luminance over the person over ours (0.67 on the 4 people of
# data/evalval512)
ALBEDO_LEVEL_RMS_STOPS = 0.70


def albedo_level_note(gain: float) -> dict:
    """The report's word on the albedo's level: where it came from, how far the input light's
    own level was from it (stops, > 0: the photo over the light's shading was brighter than the
    net's albedo) and the error to expect (a photo cannot tell a dark outfit in bright light
    from a light one in dim light; docs/RESULTS.md, "The input light and the albedo's level")."""
    return {"source": "the de-lighting net's albedo (its mean over the person)",
            "light_vs_net_stops": round(float(-np.log2(gain)), 3) if gain > 0 else None,
            "expected_error_stops": ALBEDO_LEVEL_RMS_STOPS}


def input_shadow_step(options) -> int:
    """The pixel step of the rays for the solved input light's shading: with `--shadows half`
    a grid of about INPUT_SHADOW_GRID pixels across the crop (never finer than the target's
    step), with `full` every pixel."""
    step = SHADOW_STEP[options.shadows]
    return max(step, options.resolution // INPUT_SHADOW_GRID) if options.shadows == "half" else step


# The light solve samples about this many of the person's pixels (a regular grid), with this
# many cosine-weighted visibility rays each. 2000 x 32 scored as 4000 x 64 on 150 validation
# scenes at 256 (`--albedo solve --use-gt-mask`, relit / albedo 18.13 / 18.80 vs 18.12 / 18.80)
# at a quarter of the rays: the de-lighting stage 0.85 -> 0.58 s at 512.
SOLVE_PIXELS = 2000
SOLVE_SAMPLES = 32
# A pixel whose photo reaches this (linear, any channel) is clipped: left out of the solve
SOLVE_CLIPPED = 0.95
# Albedo below this (the net's, channel mean) says little about the light: left out
SOLVE_DARK_ALBEDO = 0.03
# The solve's albedo: the net's albedo averaged over each of this many regions of the person
# (inverse.solve_light_by_regions: k-means on the photo's chromaticity and the net's
# luminance), solved again with the light SOLVE_REGION_ROUNDS times; 0 regions: the net's albedo
# itself. The net leaves part of the shading in its albedo, which the solve then explains away;
# averaged over a garment that part mostly cancels. At the solve's pixels (`python
# bench/light_levers.py levers data/lightlevers/S`, albedo dB at the oracle level / light
# direction error): validation 20.09 / 32.1 deg -> 20.25 / 28.4 (6 regions, 0 rounds), 20.24 /
# 28.6 (1 round), 20.21 / 28.7 (4); 100 training-pose scenes 19.94 / 33.0 -> 20.15 / 32.7, 20.18
# / 30.5, 20.16 / 30.6; 3 / 12 regions (4 rounds) 20.26 / 20.08 on validation. Through the
# pipeline (`relight eval data/evalval512 --use-gt-mask`, relit / albedo): 18.313 / 17.548 ->
# 18.393 / 17.640 (0 rounds: relit better in 15 of 20 scenes, albedo in 19), 18.377 / 17.612 (4
# rounds, ~0.4 s more). Test (reported, not chosen on): 23.08 -> 23.36 (0), 23.58 (1), 23.60 (4).
SOLVE_REGIONS = 6
SOLVE_REGION_ROUNDS = 0


def solve_input_light(frame: Frame, net_albedo: np.ndarray, options, models: Models) -> np.ndarray:
    """The input light by inverse rendering (relightcli.render.inverse): the light transport
    of a grid of the person's pixels on the same surfaces the target shading is traced on
    (mesh_transport), the net's albedo there averaged over each region of the person
    (SOLVE_REGIONS) as the albedo, the net's light as the prior.
    Pixels on the 2-px outline, clipped or with a dark albedo are left out. Returns the
    (16, 32, 3) light the albedo is divided by and the `light` layer's (light_layer);
    frame.notes["delight"] gets the solve's residual and sizes."""
    from relightcli.render.inverse import solve_light, solve_light_by_regions

    ensure_scenes(frame, options, models)  # built here, used by the target's shading too
    start = time.perf_counter()
    pixels = solve_pixels(frame)
    transport = mesh_transport(frame, pixels, options.seed)
    photo = frame.crop.reshape(-1, 3)[pixels].astype(np.float64)
    albedo = net_albedo.reshape(-1, 3)[pixels].astype(np.float64)
    usable = (photo.max(axis=1) < SOLVE_CLIPPED) & (albedo.mean(axis=1) >= SOLVE_DARK_ALBEDO)
    if SOLVE_REGIONS:
        solve = solve_light_by_regions(transport, photo, albedo, usable.astype(np.float64), frame.light, SOLVE_REGIONS,
                                       SOLVE_REGION_ROUNDS)
    else:
        solve = solve_light(transport, photo, albedo, usable.astype(np.float64), frame.light)
    light = grey_light(solve.light)
    net_level, level = (float(np.mean(x @ compose.LUMINANCE)) for x in (frame.light, light))
    frame.notes["delight"] = {
        "light": "inverse rendering" if solve.pixels else "no usable pixel: the net's light, made grey",
        "pixels": solve.pixels, "albedo_regions": SOLVE_REGIONS, "residual": [round(r, 4) for r in solve.residual],
        "level_vs_net": round(level / net_level, 4) if net_level > 0 else None,
        "seconds": round(time.perf_counter() - start, 4)}
    return light, light_layer(light, grey_light(frame.light), transport)


# A texel the solve's pixels see less than this share of the most seen texel's total
# transport is the prior's in the `light` layer (blended linearly up to it)
LAYER_SEEN_SHARE = 0.02


def light_layer(solved: np.ndarray, prior: np.ndarray, transport) -> np.ndarray:
    """The `light` layer: the solved light where the person's pixels see it, the prior (the
    de-lighting net's light, grey, at the solved light's level over the seen texels) where
    they hardly do (LAYER_SEEN_SHARE); the albedo is divided by the solved light's shading,
    which those texels barely change. The solve fills the unseen texels (behind the person)
    from its smoothness, 1.3-13x too bright. Against the true input light (`python
    bench/light_solve.py`, true mask; log-L2 / SH-2 error / correlation / direction): 20
    validation scenes at 512 1.535 / 0.788 / 0.242 / 32.1 deg -> 1.509 / 0.770 / 0.268 / 32.4
    deg; 40 training-split scenes 1.393 / 0.806 / 0.281 / 25.4 -> 1.353 / 0.768 / 0.306 / 25.0
    (test: docs/RESULTS.md). The whole is then blurred on the sphere (LAYER_BLUR_DEG)."""
    seen = np.maximum(transport.matrix, 0.0).sum(axis=0)
    if not seen.max() > 0:
        return sphere_blur(solved, LAYER_BLUR_DEG)
    weight = np.clip(seen / (LAYER_SEEN_SHARE * seen.max()), 0.0, 1.0).reshape(solved.shape[:2] + (1,))
    have, want = float((prior * weight).sum()), float((solved * weight).sum())
    scaled = prior * np.float32(want / have) if have > 0 else solved
    return sphere_blur(weight * solved + (1.0 - weight) * scaled, LAYER_BLUR_DEG)


# The `light` layer is blurred on the sphere by a Gaussian of this width: the solve fixes only
# what a person's shading shows (low frequencies), and its non-negative texels came out as a
# checkerboard of blotches the shading cannot tell from their blur. Against the true input
# light (`light_levers` caches, the product's solve; log-L2 / correlation / SH-2 error, and the
# person's shading under the blurred layer against the unblurred, RMS stops): validation 1.470
# / 0.305 / 0.718 -> 8 deg 1.418 / 0.320 / 0.725, 0.021; 12 deg 1.398 / 0.325 / 0.735, 0.043;
# training-pose scenes 1.463 / 0.280 / 0.757 -> 8 deg 1.354 / 0.300 / 0.758, 0.042; 12 deg
# 1.312 / 0.311 / 0.761, 0.072. The albedo is divided by the unblurred light, as before.
LAYER_BLUR_DEG = 8.0


def sphere_blur(light: np.ndarray, sigma_deg: float) -> np.ndarray:
    """(H, W, 3) float32 equirectangular light blurred on the sphere: each texel the solid-
    angle weighted mean of all texels, weighted exp((cos(angle) - 1) / sigma^2) (a Gaussian of
    the angle for small angles); its energy over the sphere kept to within the weights' spread.
    sigma_deg 0: the light as it is."""
    if not sigma_deg > 0:
        return np.asarray(light, np.float32)
    return (_blur_kernel(light.shape[0], light.shape[1], float(sigma_deg))
            @ light.reshape(-1, light.shape[-1]).astype(np.float64)).reshape(light.shape).astype(np.float32)


@functools.lru_cache(maxsize=4)
def _blur_kernel(height: int, width: int, sigma_deg: float) -> np.ndarray:
    from relightcli.io.envmap import texel_directions, texel_solid_angles

    directions = texel_directions(height, width).reshape(-1, 3)
    omega = texel_solid_angles(height, width).reshape(-1)
    sigma = np.radians(sigma_deg)
    kernel = np.exp((directions @ directions.T - 1.0) / (sigma * sigma)) * omega[None, :]
    return kernel / kernel.sum(axis=1, keepdims=True)


def grey_light(light: np.ndarray) -> np.ndarray:
    """The solved light (16, 32, 3) made colourless, its shape and luminance kept: each channel
    scaled so that the three have the same mean over the texels. The solve divides the photo
    by the net's albedo, which greys strongly coloured clothes, so their colour went into the
    solved light and out of the albedo; a white-balanced photo's light is about grey. Measured
    (`relight eval DATA --use-gt-mask`, relit / albedo dB): the solve's own colour against the
    de-lighting net's light's (the earlier choice), 150 validation scenes at 256 18.05 / 18.73 ->
    18.12 / 18.80, test (data/eval512) 18.06 / 18.61 -> 19.24 / 20.18; the net's colour against
    grey, 150 at 256 (seed 7) 17.952 / 18.303 -> 17.973 / 18.335 (albedo better in 114), 20 at
    512 17.976 / 17.213 -> 18.013 / 17.271 (16 of 20), 120 in the training split's poses 17.112
    / 17.761 -> 17.110 / 17.760. The net's colour is further from the true input light's mean
    colour than grey is (RMS of the log red/green and blue/green ratios' error 0.203 / 0.225 /
    0.265 against 0.186 / 0.207 / 0.262 on those three sets). A light with a black channel is
    kept."""
    have = light.reshape(-1, 3).mean(axis=0)
    if not (have > 0).all():
        return light
    gain = float(have @ compose.LUMINANCE) / have
    return (light * gain).astype(np.float32)


def solve_pixels(frame: Frame) -> np.ndarray:
    """Flat crop indices of a regular grid (about SOLVE_PIXELS) over the person's pixels that
    every traced surface covers, 2 px inside the outline (where the photo mixes in the
    background)."""
    inside = frame.crop_mask > 0.5
    core = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
    core &= frame.hits.mask
    if frame.body_hits is not None:
        core &= frame.body_hits.mask | ~body_shading_pixels(frame)
    stride = max(1, int(np.sqrt(core.sum() / SOLVE_PIXELS)))
    grid = np.zeros_like(core)
    grid[::stride, ::stride] = True
    return np.flatnonzero(core & grid)


def mesh_transport(frame: Frame, pixels: np.ndarray, seed: int):
    """The light transport (relightcli.render.inverse.Transport) of `pixels`, weighted over the
    reconstruction and the fitted bodies as the target shading is (trace_shading)."""
    from relightcli.render.inverse import light_transport

    transport = light_transport(frame.scene, frame.hits, pixels, samples=SOLVE_SAMPLES, seed=seed, lift=SHADOW_LIFT)
    if frame.body_scene is None:
        return transport
    body = light_transport(frame.body_scene, frame.body_hits, pixels, samples=SOLVE_SAMPLES, seed=seed,
                           lift=SHADOW_LIFT)
    weight = body_weight(frame).reshape(-1)[pixels][:, None]
    transport.matrix = ((1.0 - weight) * transport.matrix + weight * body.matrix).astype(np.float32)
    return transport
