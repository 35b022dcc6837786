"""Geometry: the person's front and back normals and depth from the geometry net (on the fitted
bodies' maps where a fit converged), ambient occlusion, and the watertight mesh reconstructed from
the two depth maps."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from relightcli import compose
from relightcli.compose import fill_uncovered
from relightcli.stages.body import body_shading_pixels
from relightcli.stages.frame import Frame, Models, net_side, resample, unit


# The nets whose maps are averaged with their maps of the mirrored crop (mirrored back): two
# runs each instead of one (0.1-0.2 s more at 512 on a slow day). Chosen on the 150
# validation scenes at 256 (`relight eval data/evalval256 --resolution 256 --use-gt-mask`,
# relit / albedo / shading dB, normals): none 18.13 / 18.80 / 19.17, 22.70 deg; the geometry
# net 18.14 / 18.81 / 19.22, 22.41; both 18.15 / 18.83 / 19.22, 22.41 (normals better in 116
# of 150 scenes, shading in 96). Test (data/eval512): relit / albedo 18.82 / 19.74 -> 18.90 /
# 19.88, normals 19.9 -> 19.7 deg.
MIRROR_AVERAGED = ("geometry", "delight")


def mirror(image: np.ndarray, vectors: tuple = ()) -> np.ndarray:
    """(H, W[, C]) image mirrored left-right (x -> -x in the camera frame), with the x component
    negated of each 3-vector whose first channel is in `vectors` (0 for a normal map). A
    lat-long light mirrors the same way, its texel columns reversed (DESIGN.md's map: u = 1/2 +
    atan2(x, -z) / 2 pi, so x -> -x takes u to 1 - u)."""
    out = np.ascontiguousarray(image[:, ::-1])
    for channel in vectors:
        out[..., channel] = -out[..., channel]
    return out


def average_geometry(g, mirrored):
    """The mean of a geometry net's GeometryMaps of a crop and `mirrored`, its maps of the
    mirrored crop: mirrored back, normals renormalised."""
    return replace(g, front_normal=unit(g.front_normal + mirror(mirrored.front_normal, (0,))),
                   back_normal=unit(g.back_normal + mirror(mirrored.back_normal, (0,))),
                   front_depth=0.5 * (g.front_depth + mirror(mirrored.front_depth)),
                   back_depth=0.5 * (g.back_depth + mirror(mirrored.back_depth)),
                   mask=0.5 * (g.mask + mirror(mirrored.mask)))


# The front normals are smoothed inside the person by a Gaussian of this share of the crop's
# side (6 px at 512) before the outline bends them: the nets' maps carry pixel noise that the
# shading inherits. Chosen on validation (true mask; relit / albedo / shading dB, normals'
# degrees; sigma at 512, half of it in pixels at 256):
#           20 at 512                      120 at 256 in training poses
#   none    18.144 / 17.354 / 21.625, 16.27  17.281 / 17.939 / 18.083, 25.44
#   2 px    18.149 / 17.358 / 21.654, 16.22  -
#   4 px    18.152 / 17.359 / 21.686, 16.20  17.301 / 17.951 / 18.108, 25.31
#   6 px    18.156 / 17.361 / 21.704, 16.24  17.304 / 17.951 / 18.112, 25.29
#   8 px    18.157 / 17.365 / 21.706, 16.34  17.301 / 17.944 / 18.109, 25.36
# 150 at 256: none 18.132 / 18.507 / 20.032, 20.31; 4 px 18.150 / 18.523 / 20.056, 20.22; 6 px
# 18.149 / 18.521 / 20.046, 20.25.
NORMAL_SIGMA = 6 / 512


def stage_geometry(frame: Frame, options, models: Models) -> None:
    """Front/back normals and depth of the person in the crop. With a converged body fit
    (stage_body_maps) the prior net refines the fitted bodies' maps into the clothed person's
    (relightcli.nets.geometry.GeometryPriorNet); without one, the net from the image alone.
    Both run on the mirrored crop too (MIRROR_AVERAGED). The note says which ran and why. The
    front normals are then smoothed inside the mask and bent toward the silhouette's near its
    outline."""
    from relightcli.geometry.silhouette import blend_silhouette_normals
    from relightcli.geometry.smoothing import smooth_normals
    from relightcli.nets.geometry import prior_channels

    maps = frame.body_maps
    with_prior = maps is not None and models.has("geometry_prior")
    net = models.get("geometry_prior" if with_prior else "geometry")
    side = net_side(net, options.resolution)
    crop = resample(frame.crop, side)
    prior = (prior_channels(maps.mask, maps.front_normal, maps.back_normal, maps.front_depth,
                            maps.back_depth, side),) if with_prior else ()
    g = net.predict(crop, *prior)
    if "geometry" in MIRROR_AVERAGED:  # the prior's front and back normals mirror too
        g = average_geometry(g, net.predict(mirror(crop), *(mirror(p, (0, 3)) for p in prior)))
    if with_prior:
        frame.notes["geometry"] = {"net": "geometry_prior", "prior": "fitted bodies"}
    else:
        why = "no geometry_prior model" if maps is not None else "no converged body fit"
        frame.notes["geometry"] = {"net": "geometry", "prior": f"none: {why}"}
    if side != options.resolution:
        size = options.resolution
        g = replace(g, front_normal=unit(resample(g.front_normal, size)), back_normal=unit(resample(g.back_normal, size)),
                    front_depth=resample(g.front_depth, size), back_depth=resample(g.back_depth, size),
                    mask=resample(g.mask, size))
    # The nets' normals are smoothed inside the person (NORMAL_SIGMA), then, near the outline,
    # where the surface turns away from the camera, pulled toward the silhouette's
    # (relightcli.geometry.silhouette)
    inside = frame.crop_mask > 0.5
    front = smooth_normals(g.front_normal, inside, NORMAL_SIGMA * options.resolution)
    beyond = compose.outside_photo(frame.box, *frame.image.shape[:2])
    g = replace(g, front_normal=blend_silhouette_normals(front, inside, beyond))
    frame.geometry = g
    frame.normal = g.front_normal * (frame.crop_mask[..., None] > 0.5)


# Where a body fit converged and the AO prior net is not in the models folder, the AO layer
# blends the net's map with the fitted bodies' own AO, ray-traced (BODY_AO_SPP samples at every
# other pixel of every other row, then upsampled: AO is smooth), the bodies' share
# BODY_AO_WEIGHT (the AO prior net, shipped, beats the blend: models/MODEL_CARD.md). AO MAE
# over the person (python bench/bench_ao.py DATA --split S --weights 0,0.5,0.7,1): the 20
# validation renders at 512 (16 fitted) 0.0642 (net), 0.0564, 0.0554, 0.0566 (bodies alone):
# 0.7 chosen; the 20 test renders (20 fitted) 0.0844 -> 0.0833. The refinement net keeps
# reading the net's map, which it was trained on: fed the blend it lost 0.08 dB of shading on
# validation (true mask, relit / shading 16.63 / 19.80 -> 16.58 / 19.72).
BODY_AO_WEIGHT = 0.7
BODY_AO_SPP = 32


def stage_ao(frame: Frame, options, models: Models) -> None:
    """Ambient occlusion in [0, 1]: the AO net's map from the crop (frame.ao_net, the
    refinement's input, the map it was trained on). When the AO layer is asked for and a body
    fit converged, the layer (frame.ao) uses the fitted bodies' ray-traced AO (body_ao): the AO
    prior net's map from the crop, the bodies' maps and that AO (relightcli.nets.geometry.
    AOPriorNet) when the models folder has it, else the AO net's map blended with the bodies'
    AO over those people."""
    from relightcli.nets.geometry import ao_prior_channels, prior_channels

    net = models.get("ao")
    side = net_side(net, options.resolution)
    frame.ao_net = resample(net.predict(resample(frame.crop, side)), options.resolution)
    frame.ao = frame.ao_net
    if "ao" not in options.outputs or frame.body_scene is None:
        return
    usable = body_shading_pixels(frame)
    if models.has("ao_prior"):
        prior_net = models.get("ao_prior")
        side = net_side(prior_net, options.resolution)
        # traced at every other pixel of the net's side, as the data factory traced it
        body = body_ao(frame, options.seed, step=max(1, 2 * options.resolution // side))
        if body is not None:
            maps = frame.body_maps
            prior = ao_prior_channels(prior_channels(maps.mask, maps.front_normal, maps.back_normal,
                                                     maps.front_depth, maps.back_depth, side), body * usable)
            frame.ao = resample(prior_net.predict(resample(frame.crop, side), prior), options.resolution)
            frame.notes["ao"] = {"net": "ao_prior"}
        return
    body = body_ao(frame, options.seed)
    if body is not None:
        weight = np.float32(BODY_AO_WEIGHT) * usable
        frame.ao = ((1.0 - weight) * frame.ao_net + weight * body).astype(np.float32)
        frame.notes["ao"] = {"net": "ao", "body_weight": BODY_AO_WEIGHT}


def body_ao(frame: Frame, seed: int, step: int = 2) -> np.ndarray | None:
    """(R, R) float32: the fitted bodies' ambient occlusion (integrator.ambient_occlusion,
    cosine-weighted, unlimited distance), traced at every `step`-th pixel of every `step`-th
    row and upsampled (AO is smooth); person pixels the bodies do not cover take their nearest
    covered pixel's. None when the bodies cover none of the traced pixels."""
    from dataclasses import replace

    from relightcli.render.integrator import ambient_occlusion

    hits = frame.body_hits
    grid = np.zeros_like(hits.mask)
    grid[::step, ::step] = True
    if not (hits.mask & grid).any():
        return None
    traced = ambient_occlusion(frame.body_scene, replace(hits, mask=hits.mask & grid), spp=BODY_AO_SPP, seed=seed)
    coarse = fill_uncovered(traced.mean[::step, ::step, 0], traced.mask[::step, ::step],
                            np.ones(grid[::step, ::step].shape, bool))
    side = frame.crop_mask.shape[0]
    return np.clip(cv2.resize(coarse, (side, side), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


# The reconstruction's mesh is built on every MESH_STEP-th pixel of the crop (its maps come
# from nets that see 256 pixels: a 512 crop's maps are enlarged, a finer grid adds triangles,
# not detail) and smoothed MESH_SMOOTHING_STEPS cotangent steps (the paper's 10 on its grid).
# Chosen on validation (`relight eval data/evalval512 --use-gt-mask`, relit / shading dB):
# every pixel, 10 steps 16.68 / 20.08 (the earlier default); every second pixel, 3 / 10 / 20 /
# 40 / 80 steps 16.65 / 19.98, 16.76 / 20.28, 16.81 / 20.43, 16.82 / 20.43, 16.80 / 20.29;
# every pixel, 40 steps 16.82 / 20.47; without the true mask 16.15 / 18.08 -> 16.25 / 18.29.
# Test (data/eval512): true mask 18.13 / 18.88 -> 18.06 / 19.00, own mask 17.91 / 17.83 ->
# 17.89 / 18.00. The stage 0.08 -> 0.02 s at 512, the ray tracer's scene a quarter the size.
# Once shadow rays were lifted off the triangles (SHADOW_LIFT), less smoothing paid, true
# mask, relit / albedo / shading: 150 validation scenes at 256, 10 steps 18.27 / 18.86 / 19.32
# against 20 steps 18.20 / 18.84 / 19.21 (better in 118, 110, 122 of 150); the 20 at 512, 10 /
# 20 / 40 steps 17.67 / 17.12 / 20.75, 17.67 / 17.13 / 20.70, 17.64 / 17.12 / 20.61; and 5
# steps against 10: 150 at 256 18.30 / 18.87 / 19.38 (shading better in 112 of 150), 20 at 512
# 17.67 / 17.12 / 20.76.
MESH_STEP, MESH_SMOOTHING_STEPS = 2, 5


def stage_reconstruct(frame: Frame, options, models: Models) -> None:
    """Double-sided depth on a grid of every MESH_STEP-th crop pixel (shrink_inside), smoothed
    inside the person (see smoothing.DEPTH_SIGMA) -> watertight mesh in the crop camera frame,
    then MESH_SMOOTHING_STEPS steps of cotangent Laplacian smoothing."""
    from relightcli.geometry.mesh import reconstruct_mesh
    from relightcli.geometry.smoothing import DEPTH_SIGMA, smooth_depth, smooth_mesh

    g = frame.geometry
    side = max(frame.crop_mask.shape[0] // MESH_STEP, 2)
    mask = shrink(frame.crop_mask, side)
    sigma = DEPTH_SIGMA * side
    front = smooth_depth(shrink_inside(g.front_depth, frame.crop_mask, side), mask, sigma)
    back = np.minimum(smooth_depth(shrink_inside(g.back_depth, frame.crop_mask, side), mask, sigma), front)
    mesh = reconstruct_mesh(mask, front, back, compose.CROP_RECT)  # the back never lies in front
    frame.mesh = smooth_mesh(mesh, steps=MESH_SMOOTHING_STEPS)
    frame.notes["reconstruct"] = {"vertices": int(len(frame.mesh.vertices)), "faces": int(len(frame.mesh.faces))}


def shrink(image: np.ndarray, side: int) -> np.ndarray:
    """(side, side, ...) float32 area average of a square map (R, R, ...)."""
    import cv2

    return cv2.resize(np.ascontiguousarray(image, np.float32), (side, side), interpolation=cv2.INTER_AREA)


def shrink_inside(values: np.ndarray, mask: np.ndarray, side: int) -> np.ndarray:
    """(side, side) float32 area average of a square map (R, R) over the soft person mask
    (R, R): each coarse pixel the mean of its fine pixels weighted by the mask, so depths
    outside the person do not leak into its outline (0 where the mask is 0)."""
    weight = np.asarray(mask, np.float32)
    total, coverage = shrink(np.asarray(values, np.float32) * weight, side), shrink(weight, side)
    return np.where(coverage > 0, total / np.where(coverage > 0, coverage, 1.0), 0.0).astype(np.float32)
