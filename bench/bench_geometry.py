"""Benchmark of the body reconstruction: speed and error against ground truth.

Ground truth: the MakeHuman base body (`g body` faces) seen by a 512x512 orthographic crop,
rendered into the maps a geometry net predicts (mask, front/back depth, front/back normals) by
embreex ray casts (tests/geometry/geometry_truth.py). Variants rebuild a mesh from those maps:

  depth            front/back depth -> reconstruct_mesh -> 10 cotangent smoothing steps
  depth raw        the same without smoothing
  normals          front/back normals -> integrate_normals (no prior, back meets front on the
                   silhouette, then shifted by the ground-truth mean: normals carry no offset)
  noisy depth      depth + N(0, sigma) per pixel (a net's error) -> mesh -> smoothing
  noisy d+normals  normals integrated with the noisy depth as prior -> mesh -> smoothing

Metrics: front-depth error on the pixels both meshes cover (re-rendered), symmetric Chamfer
distance (mean of both directions, 100k surface samples), and shading PSNR: the project's
integrator (relightcli.render: Scene, render_pixel_geometry, shade_environment, direct light,
128 spp Sobol, same seed) on the ground-truth mesh and on the reconstruction, same crop at
256x256, DESIGN.md protocol (mask = both hit, divide by p95 of the truth / 0.8, clip, sRGB).

Run: python bench/bench_geometry.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.spatial
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "geometry"))

import geometry_truth  # noqa: E402
from relightcli.geometry.mesh import reconstruct_mesh  # noqa: E402
from relightcli.geometry.normal_integration import (  # noqa: E402
    double_sided_depth,
    integrate_normals,
)
from relightcli.geometry.smoothing import smooth_mesh  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.io.images import linear_to_srgb  # noqa: E402
from relightcli.metrics import psnr  # noqa: E402

ENVMAPS = ("noon_grass_1k.hdr", "studio_small_05_1k.hdr")


def time_best(function, repeats):
    """(best, median) seconds over `repeats` calls, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return min(times), float(np.median(times)), result


def chamfer(a: trimesh.Trimesh, b: trimesh.Trimesh, samples=100_000):
    """Symmetric mean closest-point distance between surface samples, world units."""
    pa, _ = trimesh.sample.sample_surface(a, samples, seed=0)
    pb, _ = trimesh.sample.sample_surface(b, samples, seed=1)
    d_ab, _ = scipy.spatial.cKDTree(pb).query(pa)
    d_ba, _ = scipy.spatial.cKDTree(pa).query(pb)
    return 0.5 * (d_ab.mean() + d_ba.mean())


def depth_error(mesh, truth, size):
    """Mean |front depth error| over pixels both the mesh and the truth cover, world units."""
    maps = geometry_truth.render_maps(mesh, truth.rect, size, size)
    both = maps.mask & truth.mask
    return float(np.abs(maps.front_depth - truth.front_depth)[both].mean())


def shading(mesh, rect, size, light):
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.integrator import shade_environment
    from relightcli.render.scene import Scene

    scene = Scene.from_trimesh(mesh)
    geometry = render_pixel_geometry(scene, rect, (size, size))
    return shade_environment(scene, geometry, light, spp=128, seed=0).mean, geometry.mask


def shading_psnr(truth_shading, truth_mask, shading_, mask):
    both = truth_mask & mask
    scale = np.percentile(truth_shading[truth_mask], 95) / 0.8
    encode = lambda s: linear_to_srgb(np.clip(s / scale, 0.0, 1.0))  # noqa: E731
    return psnr(encode(truth_shading), encode(shading_), both)


def variants(truth, sigma, rng):
    m = truth
    noisy_front = m.front_depth + rng.normal(0.0, sigma, m.front_depth.shape)
    noisy_back = m.back_depth + rng.normal(0.0, sigma, m.back_depth.shape)

    def build(front, back):
        return reconstruct_mesh(m.mask, front, back, m.rect).to_trimesh()

    def from_normals():
        front, back = double_sided_depth(m.front_normal, m.back_normal, m.mask, m.rect)
        shift = np.mean(m.front_depth[m.mask] - front[m.mask])
        return smooth_mesh(reconstruct_mesh(m.mask, front + shift, back + shift, m.rect).to_trimesh())

    def from_noisy_fusion():
        front = integrate_normals(m.front_normal, m.mask, m.rect, depth_prior=noisy_front)
        back = integrate_normals(m.back_normal, m.mask, m.rect, depth_prior=noisy_back)
        return smooth_mesh(reconstruct_mesh(m.mask, front, back, m.rect).to_trimesh())

    return {
        "depth": lambda: smooth_mesh(build(m.front_depth, m.back_depth)),
        "depth raw": lambda: build(m.front_depth, m.back_depth),
        "normals": from_normals,
        "noisy depth": lambda: smooth_mesh(build(noisy_front, noisy_back)),
        "noisy d+normals": from_noisy_fusion,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--shade-size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="timing only, no metrics")
    args = parser.parse_args()

    body = geometry_truth.makehuman_body()
    if body is None:
        sys.exit(f"MakeHuman data not found at {geometry_truth.BODY_OBJ}")
    rect = geometry_truth.square_rect(body)
    truth = geometry_truth.render_maps(body, rect, args.size, args.size)
    pixel = (rect[1] - rect[0]) / args.size
    print(f"body: {len(body.faces)} faces, height {np.ptp(body.vertices[:, 1]):.2f}; crop "
          f"{args.size}x{args.size}, {truth.mask.sum()} mask pixels, pixel {pixel:.4f}")

    m = truth
    build = lambda: reconstruct_mesh(m.mask, m.front_depth, m.back_depth, m.rect).to_trimesh()  # noqa: E731
    best_b, med_b, mesh = time_best(build, args.repeats)
    best_s, med_s, _ = time_best(lambda: smooth_mesh(mesh), args.repeats)
    best_t, med_t, _ = time_best(lambda: smooth_mesh(build()), args.repeats)
    best_n, med_n, _ = time_best(lambda: integrate_normals(m.front_normal, m.mask, m.rect), 1)
    print(f"\nmesh: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces")
    print(f"{'stage':34s} {'best ms':>8s} {'median ms':>10s}")
    rows = (("reconstruct_mesh", best_b, med_b), ("smooth_mesh (10 steps)", best_s, med_s),
            ("reconstruct + smooth", best_t, med_t),
            ("integrate_normals (one side)", best_n, med_n))
    for name, best, med in rows:
        print(f"{name:34s} {best * 1e3:8.1f} {med * 1e3:10.1f}")
    if args.quick:
        return

    from relightcli.render.environment import EnvironmentLight

    lights = {name: EnvironmentLight(load_envmap(geometry_truth.DATA / "hdri" / name))
              for name in ENVMAPS}
    references = {name: shading(body, rect, args.shade_size, light)
                  for name, light in lights.items()}
    rng = np.random.default_rng(0)
    sigma = pixel
    print(f"\nnoise sigma = {sigma:.4f} (one pixel); Chamfer and depth error in pixels "
          f"({pixel:.4f} world units)")
    header = f"{'variant':18s} {'depth err px':>12s} {'chamfer px':>11s} {'watertight':>10s}"
    header += "".join(f" {'PSNR ' + name.split('_')[0]:>14s}" for name in ENVMAPS)
    print(header)
    for name, make in variants(truth, sigma, rng).items():
        mesh = make()
        row = (f"{name:18s} {depth_error(mesh, truth, args.size) / pixel:12.3f} "
               f"{chamfer(mesh, body) / pixel:11.3f} {str(mesh.is_watertight):>10s}")
        for env_name, light in lights.items():
            ref, ref_mask = references[env_name]
            value, value_mask = shading(mesh, rect, args.shade_size, light)
            row += f" {shading_psnr(ref, ref_mask, value, value_mask):14.2f}"
        print(row, flush=True)


if __name__ == "__main__":
    main()
