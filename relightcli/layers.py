"""The output layers a run can write: one table, read by the CLI (choices, help) and the batch
planner (file names). Light-weight on purpose: `relight --help` imports it."""

from __future__ import annotations

from dataclasses import dataclass


# Default ray-tracing effort: stop each pixel at 4% relative standard error, at most 32
# samples. Monte Carlo noise at that level is far below the networks' errors: on the 20 eval
# scenes the relit image and the shading score within 0.02 dB of 2% / 64 samples (true mask:
# relit 15.049 vs 15.056 dB, shading 17.529 vs 17.545 dB), at 1.19 instead of 1.87 s of ray
# tracing for a 512 crop. `--target-error` / `--spp` ask for more.
DEFAULT_TARGET_ERROR, DEFAULT_SPP_CAP = 0.04, 32

# Where rays for cast shadows and occlusion are traced (stages.shading.traced): "half" every second
# pixel of the crop in both directions, the visibility found there applied to every pixel's
# own unoccluded shading (the eval scores within 0.07 dB of "full", the ray tracing stage
# takes 0.6x the time); "full" every pixel.
SHADOW_STEP = {"half": 2, "full": 1}
# The solved input light's shading, which the albedo divides by (`--albedo solve`), comes from a
# 16 x 32 map whose texels span 11 degrees: its shadows are soft, and "half" traces it on a grid
# of about this many pixels across the crop (every fourth pixel at 512, every second at 256:
# stages.delight.input_shadow_step)
INPUT_SHADOW_GRID = 128
DEFAULT_SHADOWS = "half"

# Default working resolution: the paper's 512-pixel person crop, although the shipped nets
# trained on 256-pixel crops. Measured on 20 test scenes rendered at 512 (true mask, no
# refinement): relit 15.32 vs 15.25 dB at a 256 crop, albedo 15.96 vs 15.75, shading 16.80 vs
# 17.44; with the predicted mask relit 13.23 vs 13.17 dB. The same quality by the protocol, but
# the output keeps twice the detail, and a full-body face (~35 px at 512, ~17 at 256) is large
# enough for the face stage. `--resolution 256` is twice as fast.
DEFAULT_RESOLUTION = 512


@dataclass(frozen=True)
class Layer:
    name: str
    suffix: str  # appended to the input's stem; "" for the relit image itself
    extension: str  # default extension; the relit image takes -o's extension when -o is a file
    description: str


LAYERS = {
    layer.name: layer
    for layer in (
        Layer("relit", "", ".png", "the person relit under --hdr (sRGB PNG; .exr/.hdr keep HDR)"),
        Layer("albedo", "_albedo", ".png", "de-lit reflectance, 16-bit sRGB PNG"),
        Layer("normal", "_normal", ".png", "camera-space normals stored as (n+1)/2, 16-bit PNG"),
        Layer("ao", "_ao", ".png", "ambient occlusion in [0,1], 16-bit grey PNG"),
        Layer("shading", "_shading", ".exr", "HDR shading under --hdr, linear EXR"),
        Layer("mask", "_mask", ".png", "person mask in [0,1], 8-bit grey PNG"),
        Layer("mesh", "_mesh", ".ply", "reconstructed, smoothed full-body mesh (PLY)"),
        Layer("body_normal", "_body_normal", ".png",
              "the fitted body's camera-facing normals on the person as (n+1)/2, 16-bit PNG "
              "(black: no body)"),
        Layer("body_depth", "_body_depth", ".exr",
              "the fitted body's depth on the person, linear EXR: R front z, G back z (crop units: the crop "
              "spans [-1, 1], +z toward the camera), B 1 where a body is"),
        Layer("light", "_light", ".hdr", "estimated input lighting, 32x16 lat-long HDR (solved on the mesh, grey; "
              "--albedo ratio|net: the de-lighting net's)"),
        Layer("preview", "_preview", ".png", "one sheet: input, albedo, normal, shading, relit, input light, env"),
    )
}

DEFAULT_OUTPUTS = ("relit",)

# Shading methods: the paper (ray tracing + learned refinement), its ablation, and the SH baselines.
METHODS = ("raytrace", "raytrace-norefine", "sh9", "sh25")

# Albedo sources: the photo divided by the ray-traced shading of the input light solved by
# inverse rendering on the mesh (default), by the SH-9 shading of the de-lighting net's light,
# or the de-lighting net's own albedo head (the paper's)
ALBEDO_SOURCES = ("solve", "ratio", "net")
DEFAULT_ALBEDO = "solve"

# Inputs a directory scan picks up (lower-case extensions).
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp", ".exr", ".hdr")

# Files an output image can be written as (relightcli.io.images writes these).
OUTPUT_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".hdr")
