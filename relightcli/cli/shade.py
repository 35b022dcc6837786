"""`relight shade MESH --hdr ENV -o shading.exr`: ray-traced white-Lambertian shading of a mesh.

Pixel-aligned orthographic camera looking along -Z (DESIGN.md). The default rectangle is the
mesh's x/y bounds padded by 5%. `run` returns the report dict; it never prints or exits (the
dispatcher in relightcli.cli does both).
"""

from __future__ import annotations

import argparse
import math
import os
import time
import warnings
from pathlib import Path

from relightcli.cli import MAX_SPP, RESOLUTION_RANGE, seed_value, spp_value
from relightcli.errors import InputError, OutputError, RelightError, RelightWarning, UsageError

# Below this many estimated rays forking sampling workers costs more than it saves
PARALLEL_MIN_RAYS = 1 << 21
# The largest render by default: relight's largest working crop (--resolution 2048). A render
# holds ~0.7 KB per pixel (geometry, float64 sums; 0.93 GB peak at 1024 x 1024), so this is
# ~3 GB; --max-pixels raises it
DEFAULT_MAX_PIXELS = RESOLUTION_RANGE[1] ** 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `shade` options (the common --threads/--json/--overwrite come from the caller)."""
    parser.add_argument("mesh", metavar="MESH", help="any mesh file trimesh reads (OBJ, PLY, GLB, STL, ...)")
    parser.add_argument("--hdr", required=True, metavar="ENV",
                        help="equirectangular environment map (.hdr/.exr, linear radiance, W = 2H)")
    parser.add_argument("-o", "--output", required=True, metavar="PATH",
                        help="shading image (.exr keeps linear float values)")
    parser.add_argument("--res", nargs=2, type=_side, default=(512, 512), metavar=("W", "H"),
                        help="image size in pixels (default 512 512; at most --max-pixels in all)")
    parser.add_argument("--max-pixels", type=_side, default=DEFAULT_MAX_PIXELS, metavar="N",
                        help=f"refuse a --res of more than N pixels before any work (default {DEFAULT_MAX_PIXELS}"
                             f" = {RESOLUTION_RANGE[1]}x{RESOLUTION_RANGE[1]}, relight's largest render; a "
                             "render takes ~0.7 KB of memory per pixel)")
    parser.add_argument("--rect", nargs=4, type=finite_float, default=None, metavar=("X0", "X1", "Y0", "Y1"),
                        help="world rectangle the image covers (default: mesh x/y bounds + 5%%)")
    amount = parser.add_mutually_exclusive_group()
    amount.add_argument("--spp", type=spp_value, default=None, metavar="N",
                        help=f"samples per pixel, 1..{MAX_SPP} (default 64; with --time-budget, the cap)")
    amount.add_argument("--target-error", type=_positive_finite, default=None, metavar="E",
                        help=f"stop each pixel at this relative standard error (e.g. 0.02; at most {MAX_SPP} samples)")
    parser.add_argument("--time-budget", type=_positive_finite, default=None, metavar="S",
                        help=f"stop sampling after about S seconds (at most {MAX_SPP} samples)")
    parser.add_argument("--bounces", type=int, choices=(1, 2), default=1,
                        help="1: direct light; 2: plus one diffuse interreflection")
    parser.add_argument("--albedo", type=_albedo_value, default=1.0, metavar="A",
                        help="surface albedo for the second bounce, 0..1 (default 1: white)")
    parser.add_argument("--rotate", type=finite_float, default=0.0, metavar="DEG",
                        help="turn the environment about +Y, counter-clockwise seen from above")
    parser.add_argument("--seed", type=seed_value, default=0, metavar="S", help="sampling seed >= 0 (default 0)")
    parser.add_argument("--strategy", choices=("mis", "env", "cosine", "uniform"), default="mis",
                        help="direction sampling (default mis: planned per environment)")
    parser.add_argument("--sampler", choices=("sobol", "independent"), default="sobol",
                        help="sample sequence (default sobol: randomised QMC)")
    parser.add_argument("--lift", type=_lift_value, default=0.0, metavar="EDGES",
                        help="lift shadow rays off the triangles toward the shading normals by EDGES x the "
                             "median edge length x sin(angle between shading and face normal): no "
                             "staircase of facets at a hard light's terminator on a coarse smooth-shaded "
                             "mesh (default 0: rays leave the triangles, exact to the mesh as given; "
                             "relight's own renders use 1)")
    parser.add_argument("--denoise", action="store_true",
                        help="filter the shading's Monte Carlo noise with the integrator's own per-pixel "
                             "error (adaptive Wiener filter on the visibility; the error map and the "
                             "reported error stay those before filtering)")
    parser.add_argument("--error-map", default=None, metavar="PATH",
                        help="also write the per-pixel standard error (linear, same units)")
    parser.add_argument("--mask-map", default=None, metavar="PATH",
                        help="also write the coverage mask (1 on the mesh, 0 elsewhere)")


def _lift_value(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 10.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 10 edge lengths, got {text}")
    return value


def finite_float(text: str) -> float:
    """An argparse type: a finite number (nan and inf are refused)."""
    value = float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _positive_finite(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _albedo_value(text: str) -> float:
    """An albedo: the share of light a surface reflects, 0..1 (above 1 it would create light)."""
    value = float(text)
    if not 0.0 <= value <= 1.0:  # also refuses nan
        raise argparse.ArgumentTypeError(f"must be between 0 and 1, got {text}")
    return value


def _side(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def run(args, threads: int) -> dict:
    """Render, write the requested files, return the report:
    {"spp", "rays", "seconds", "mrays_per_s", "rel_error", ...}."""
    import numpy as np

    from relightcli.io.envmap import load_envmap
    from relightcli.io.images import write_image
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.denoise import filtered_shading
    from relightcli.render.environment import EnvironmentLight
    from relightcli.render.integrator import shade_environment
    from relightcli.render.scene import Scene

    spp = _samples(args)
    outputs = _check_outputs(args)
    mesh = load_mesh(args.mesh)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RelightWarning)
        env = load_envmap(args.hdr, rotate_deg=args.rotate)
        light = EnvironmentLight(env)
        width, height = args.res
        estimated_rays = width * height * (spp or 1024) * 2
        workers = max(1, threads) if estimated_rays >= PARALLEL_MIN_RAYS else 1
        start = time.perf_counter()
        try:
            with Scene.from_trimesh(mesh) as scene:
                rect = tuple(args.rect) if args.rect is not None else _mesh_rect(scene, args.mesh)
                geometry = render_pixel_geometry(scene, rect, (width, height))
                result = shade_environment(
                    scene, geometry, light, spp=spp or MAX_SPP,
                    target_error=args.target_error, time_budget=args.time_budget,
                    strategy=args.strategy, bounces=args.bounces, albedo=args.albedo,
                    sampler=args.sampler, seed=args.seed, workers=workers, lift=args.lift)
                shading = filtered_shading(result, light, geometry.normal) if args.denoise else result.mean
        except MemoryError as exc:
            raise RelightError(f"out of memory rendering {width}x{height} pixels", path=args.mesh,
                               fix="lower --res (a render takes ~0.7 KB of memory per pixel)") from exc
        seconds = time.perf_counter() - start
        mask = geometry.mask.astype(np.float32)
        write_image(outputs["shading"], shading, alpha=mask, overwrite=args.overwrite)
        if "error" in outputs:
            write_image(outputs["error"], result.stderr, alpha=mask, overwrite=args.overwrite)
        if "mask" in outputs:
            write_image(outputs["mask"], mask, overwrite=args.overwrite, srgb=False)
    return _report(args, result, geometry, rect, width * height, seconds, outputs, caught)


def _mesh_rect(scene, mesh_path) -> tuple[float, float, float, float]:
    """The default rectangle (the mesh's x/y bounds + 5%) as plain floats; InputError naming
    the mesh when it has no width or height seen along -Z (a mesh flat in x or y)."""
    from relightcli.render.camera import default_rect

    x0, x1, y0, y1 = (float(c) for c in default_rect(scene))
    flat = [axis for axis, low, high in (("x", x0, x1), ("y", y0, y1)) if not high > low]
    if flat:
        raise InputError(f"the mesh is flat in {' and '.join(flat)} (x {x0:g}..{x1:g}, y {y0:g}..{y1:g}): "
                         "seen along -Z it covers no area", path=mesh_path,
                         fix="pass --rect X0 X1 Y0 Y1, or turn the mesh so that it faces +Z")
    return x0, x1, y0, y1


def load_mesh(path):
    """A trimesh.Trimesh from any file trimesh reads; InputError naming the file otherwise."""
    import trimesh

    if not os.path.isfile(path):
        raise InputError("mesh file not found", path=path, fix="check the path")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh: {exc}", path=path,
                         fix="give a mesh trimesh reads (OBJ, PLY, GLB, STL, OFF)") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("file holds no triangles", path=path, fix="give a triangle mesh")
    return mesh


def _samples(args):
    """The fixed samples per pixel (None: adaptive, capped at MAX_SPP), after checking the
    effort options together: the render's size against --max-pixels, the rectangle."""
    if args.spp is not None and args.spp < 1:
        raise UsageError(f"--spp must be >= 1, got {args.spp}")
    if args.target_error is not None and not args.target_error > 0:
        raise UsageError(f"--target-error must be > 0, got {args.target_error}")
    if args.time_budget is not None and not args.time_budget > 0:
        raise UsageError(f"--time-budget must be > 0, got {args.time_budget}")
    width, height = args.res
    if min(width, height) < 1:
        raise UsageError(f"--res must be positive, got {width} {height}")
    if width * height > args.max_pixels:
        raise UsageError(f"--res {width} {height} is {width * height} pixels, more than the limit of "
                         f"{args.max_pixels} (a render takes ~0.7 KB of memory per pixel)",
                         fix="lower --res, or raise the limit with --max-pixels")
    if args.rect is not None:
        x0, x1, y0, y1 = args.rect
        if not (x1 > x0 and y1 > y0):
            raise UsageError(f"--rect {x0:g} {x1:g} {y0:g} {y1:g} covers no area",
                             fix="give X0 < X1 and Y0 < Y1")
    if args.spp is None and args.target_error is None and args.time_budget is None:
        return 64
    return args.spp


def _check_outputs(args) -> dict:
    """Output paths by role, checked before any work: distinct, not an input, and files
    write_image can write (format from the extension, not a folder, a writable folder)."""
    from relightcli.io.images import check_output_path

    outputs = {"shading": args.output}
    if args.error_map:
        outputs["error"] = args.error_map
    if args.mask_map:
        outputs["mask"] = args.mask_map
    resolved = [Path(p).resolve() for p in outputs.values()]
    if len(set(resolved)) != len(resolved):
        raise OutputError("two outputs share one path", path=args.output,
                          fix="give -o, --error-map and --mask-map different names")
    inputs = {Path(args.mesh).resolve(), Path(args.hdr).resolve()}
    for path, full in zip(outputs.values(), resolved):
        if full in inputs:
            raise OutputError("output would overwrite an input", path=path, fix="choose another name")
        check_output_path(path, overwrite=args.overwrite)
    return outputs


def _report(args, result, geometry, rect, primary_rays, seconds, outputs, caught) -> dict:
    """The JSON report; seconds and Mrays/s cover the scene build, the camera and sampling."""
    rays = result.rays + primary_rays
    masked = int(geometry.mask.sum())
    spp = float(result.passes[geometry.mask].mean()) if masked else 0.0
    return {
        "spp": round(spp, 2),
        "rays": int(rays),
        "seconds": round(seconds, 4),
        "mrays_per_s": round(rays / max(seconds, 1e-9) / 1e6, 3),
        "rel_error": round(result.median_relative_error(), 5),
        "strategy": result.strategy,
        "denoised": bool(args.denoise),
        "pixels": masked,
        "resolution": list(args.res),
        "rect": [float(c) for c in rect],
        "outputs": outputs,
        "warnings": [str(w.message) for w in caught if issubclass(w.category, RelightWarning)],
    }
