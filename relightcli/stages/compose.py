"""Compose: relit = albedo x shading in the crop, and the frame turned into output layers (the
relit person over its background at the display exposure, the straight layers over black, the
preview's tiles). The image operations themselves are relightcli.compose's."""

from __future__ import annotations

import warnings

import numpy as np

from relightcli import compose
from relightcli.errors import RelightWarning
from relightcli.io.envmap import environment_view
from relightcli.io.images import row_bands
from relightcli.stages.frame import Frame, Models


def stage_compose(frame: Frame, options, models: Models) -> None:
    """relit = albedo * shading in the crop (pasted back into the full frame by the outputs).
    An all-black target environment lights nothing: shading and relit are black, whatever
    residual the refinement nets add to zero shading, and a RelightWarning says so."""
    if not np.any(frame.env):
        warnings.warn("the target environment map is all black (no light): the relit person "
                      "is black; check the map and --exposure", RelightWarning, stacklevel=2)
        frame.shading = np.zeros_like(frame.shading)
        frame.notes["compose"] = {"black_environment": True}
    frame.relit_crop = compose.relight(frame.albedo, frame.shading)


def layer_image(name: str, frame: Frame, options, hdr: bool = False):
    """(array, alpha, srgb) for an image layer, full frame. `hdr`: the file keeps linear HDR
    values (EXR/HDR), so no display exposure is applied."""
    height, width = frame.image.shape[:2]
    full = lambda crop: compose.paste_back(crop, frame.box, height, width)  # noqa: E731
    if name == "mask":
        return frame.mask, None, False
    if name in ("albedo", "shading"):  # straight layers, over black at the photo's mask (alpha)
        layer = full(getattr(frame, name))
        if name == "albedo":  # the photo's own detail, which the crop lost (the shading is smooth)
            detail = photo_detail(frame)
            for rows in row_bands(height):
                detail.apply(layer[rows], rows)
        return over_black(layer, frame.mask), None, True
    if name == "normal":
        return full((frame.normal + 1.0) * 0.5 * (frame.crop_mask[..., None] > 0.5)), None, False
    if name == "ao":
        return full(frame.ao * frame.crop_mask), None, False
    if name == "relit":
        return relit_image(frame, options, hdr)
    if name in ("body_normal", "body_depth"):
        return full(body_layer(name, frame.body_maps, options.resolution)), None, False
    raise ValueError(f"{name} is not an image layer")


def photo_detail(frame: Frame) -> compose.PhotoDetail:
    """The photo's detail the working crop lost (compose.PhotoDetail), for the relit and albedo
    layers."""
    return compose.PhotoDetail(frame.image, frame.crop, frame.box, frame.mask)


def body_layer(name: str, maps, resolution: int) -> np.ndarray:
    """(R, R, 3) crop of a body prior layer: `body_normal` (front normals as (n + 1) / 2, black
    off the bodies), `body_depth` (front z, back z, coverage in 0/1); all zero when no body fit
    converged (maps None)."""
    if maps is None:
        return np.zeros((resolution, resolution, 3), np.float32)
    covered = maps.mask[..., None]
    if name == "body_normal":
        return ((maps.front_normal + 1.0) * 0.5 * covered).astype(np.float32)
    return np.stack([maps.front_depth, maps.back_depth, maps.mask.astype(np.float32)], axis=-1)


# Display exposure of LDR outputs (see scene_exposure): a white surface facing the camera shows
# at DISPLAY_KEY (linear), so a person of albedo a facing the light shows at about a, as an
# incident-light meter exposes; the meter reads at least METER_FLOOR x the brightest direction
DISPLAY_KEY = 1.0
METER_FLOOR = 0.1


def scene_exposure(env: np.ndarray, exposure_ev: float = 0.0) -> float:
    """The display exposure of LDR outputs, from the target environment alone, never from the
    relit result (which would undo --exposure and light a person under a black map).

    An incident-light meter at the subject with its dome toward the camera (+Z), the
    photographer's rule: the factor that shows an unoccluded white surface facing the camera
    at DISPLAY_KEY, from its unoccluded shading (never less than METER_FLOOR x that of the
    brightest direction, so a map lit only from behind is not exposed for darkness). The meter
    reads the map as it was before --exposure (env / 2 ** exposure_ev), so --exposure
    multiplies the displayed linear result by exactly 2 ** exposure_ev. On the examples (skier
    photo, person mean linear luminance 0.089): 0.069 under noon_grass.hdr, 0.056 under
    kloofendal_overcast.hdr. env: (H, 2H, 3) float32 linear radiance. Returns the factor; 1.0
    for an all-black map (the person stays black; load_envmap warns).
    """
    from relightcli.io.envmap import resample_envmap, texel_directions
    from relightcli.render.environment import EnvironmentLight

    coarse = resample_envmap(env, min(64, env.shape[0])) / np.float32(2.0 ** exposure_ev)
    light = EnvironmentLight(coarse)
    normals = np.concatenate([[[0.0, 0.0, 1.0]], texel_directions(32, 64).reshape(-1, 3)])
    shading = light.irradiance(normals) @ compose.LUMINANCE
    meter = max(float(shading[0]), METER_FLOOR * float(shading.max()))
    return DISPLAY_KEY / meter if meter > 0 and np.isfinite(meter) else 1.0


def over_black(straight: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) straight colour times the (H, W) mask as alpha, in place, a band of rows at a
    time; returned."""
    for rows in row_bands(straight.shape[0]):
        straight[rows] *= mask[rows, :, None]
    return straight


def relit_image(frame: Frame, options, hdr: bool):
    """The relit person over the requested background, (rgb, alpha, srgb). EXR/HDR files keep
    the linear relit values; LDR files show them times `scene_exposure` of the target map (the
    environment view gets the same factor, so they stay consistent; a '#RRGGBB' background and
    the kept photo are shown as they are). Over the photo or the environment view a predicted
    mask is sharpened into the alpha (relit_matte); an input mask is used as it is."""
    mask = frame.mask
    matte = relit_matte(frame, options.background)
    scale = 1.0 if hdr else scene_exposure(frame.env, options.exposure_ev)
    env_view = None
    if options.background == "env":
        env_view = background_view(frame, options)
    # The environment view is made for this output only: composite over it in place.
    rgb, alpha = compose.composite_crop(frame.relit_crop, frame.box, mask, options.background,
                                        photo=frame.image, env_view=env_view, scale=scale, out=env_view,
                                        matte=matte, detail=photo_detail(frame))
    frame.notes["relit"] = {"display_exposure": scale}
    if matte is not None:
        frame.notes["relit"]["matte"] = f"the predicted mask sharpened from {matte[0]}..{matte[1]} to 0..1"
    return rgb, alpha, True


# Backgrounds over which a predicted mask is sharpened (compose.PREDICTED_MATTE): images behind
# the person. Over a colour (and as the transparent output's alpha) the mask stays the alpha:
# sharpened, the relit person over black lost on the paper's protocol (the true person's pixels
# only: relit -0.09 dB on the 20 validation scenes at 512, -0.20 on the test scenes, SSIM +0.02
# / +0.01) while it gained around the people (black +0.65 / +0.78 dB at 256 / 512)
SHARPENED_OVER = ("keep", "env")


def relit_matte(frame: Frame, background: str) -> tuple[float, float] | None:
    """The matte the relit output is composited with over `background`: compose.PREDICTED_MATTE
    for a predicted mask over an image (SHARPENED_OVER), else None (the mask as alpha)."""
    return compose.PREDICTED_MATTE if frame.mask_predicted and background in SHARPENED_OVER else None


def background_view(frame: Frame, options) -> np.ndarray:
    """The environment seen by a 60-degree camera, rendered at most 1024 wide (the map has no
    more detail than that) and resized to the photo."""
    import cv2

    height, width = frame.image.shape[:2]
    w = min(width, 1024)
    h = max(1, round(height * w / width))
    view = environment_view(frame.env, width=w, height=h, fov_deg=60.0)
    if (h, w) != (height, width):
        view = cv2.resize(view, (width, height), interpolation=cv2.INTER_LINEAR)
    return view


def preview_tiles(frame: Frame, options) -> list:
    """Input, albedo, normal, shading, relit, the estimated input light and the target
    environment, display-ready; shading and relit at the relit output's `scene_exposure`, each
    map at its own 99th percentile."""
    alpha = frame.crop_mask[..., None]  # the layers are straight: shown over black, as the files
    crop_relit = compose.crop_square(frame.relit, frame.box) * alpha
    # relit and shading under the scene's exposure (as the relit output), not re-exposed to taste
    relit_scale = shading_scale = scene_exposure(frame.env, options.exposure_ev)
    map_scale = lambda env: 0.8 / max(float(np.percentile(env @ compose.LUMINANCE, 99.0)), 1e-12)  # noqa: E731
    return [
        ("input", compose.to_display(frame.crop)),
        ("albedo", compose.to_display(frame.albedo * alpha)),
        ("normal", (frame.normal + 1.0) * 0.5 * (frame.crop_mask[..., None] > 0.5)),
        ("shading", compose.to_display(frame.shading * alpha, shading_scale)),
        ("relit", compose.to_display(crop_relit, relit_scale)),
        ("input light", compose.to_display(frame.light, map_scale(frame.light))),
        ("environment", compose.to_display(frame.env, map_scale(frame.env))),
    ]
