"""Error against run time of the environment-light integrator (not part of the test suite).

    python bench/bench_integrator.py [--res 512] [--max-spp 1024] [--workers 2] [--quick]
                                     [--strategies mis,...] [--mitsuba]
    python bench/bench_integrator.py --headline     # the 1 s / 2% target and the scaling
    python bench/bench_integrator.py --throughput   # Mrays/s against raw embreex, same rays

--mitsuba adds Mitsuba 3 (bench-only: `pip install mitsuba==3.6.4`; LLVM variant, all cores)
on the same job in the same run, rendered by Mitsuba itself (`mi.render`, see MitsubaJob):
same mesh (PLY with our vertex normals), same map texels, its `direct` integrator (MIS) on a
white diffuse BSDF, an orthographic sensor over the same rectangle and pixels, a sweep of spp.
Each renderer's error is its own Monte Carlo error (the two agree to <= 1% relative RMSE,
tests/render/test_mitsuba.py): ours against its converged reference (RQMC: the error must be
measured), Mitsuba's from two independent renders (i.i.d. samples: mean((a - b)^2) / 2 is
the squared error of one, unbiased; a reference render as converged as ours would take
Mitsuba hours), both over the masked pixels. The time each needs to reach a given relative
RMSE is interpolated (log-log) from its sweep; the ratio ours / Mitsuba is printed. Both are
timed warm, in-process (Mitsuba's kernels compiled by a first render, ours after a first
render), on the same cores. Mitsuba also shades the background pixels (one primary ray and
one map lookup each, ~78% of the frame) and jitters its samples over each pixel's area where
ours shades pixel centres: both cost it little (the error on the mask eroded by 2 pixels is
within 4% of the error on the whole mask).

--headline renders the same framing at the resolution that gives the issue's masked-pixel
count (30% of 512 x 512 = 78.6k pixels: 592 x 592 here, where the body covers 22.4%).

Renders the MakeHuman body (subdivided once with trimesh: ~107k triangles) at RES x RES
(default rectangle: the body's x/y bounds + 5%), under a hard-sun and an overcast HDR, for
strategies uniform / cosine / env / mis-nocv (MIS without the control variate) / mis at 4..max-spp samples per pixel and for target errors,
and measures wall time and error against a converged reference. The reference is rendered on
a random subset of the mask (REF_PIXELS pixels at REF_SPP samples), so errors are measured on
those pixels. Also measures Mrays/s of the integrator against raw embreex on the same kind of
rays, and scaling from 1 to 2 processes.

Writes bench/results/integrator_error_vs_time.csv and .png (log-log) and prints a table.
"""

from __future__ import annotations

import argparse
import csv
import glob
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "render"))

from render_testing import body_mesh, load_hdr  # noqa: E402  (test helpers: OBJ group, HDR reader)

from relightcli.render.camera import default_rect, render_pixel_geometry  # noqa: E402
from relightcli.render.environment import EnvironmentLight  # noqa: E402
from relightcli.render.estimators import cosine_directions, ray_origins  # noqa: E402
from relightcli.render.integrator import shade_environment  # noqa: E402
from relightcli.render.scene import Scene  # noqa: E402

HDRS = {"hard_sun": "noon_grass_1k.hdr", "overcast": "kloofendal_overcast_1k.hdr"}
# "mis" runs the planned default (sun apart, unoccluded shading as a control variate);
# "mis-nocv" the same without the control variate
STRATEGIES = ("uniform", "cosine", "env", "mis-nocv", "mis")
TARGETS = (0.08, 0.04, 0.02)
# Relative RMSEs at which the time to reach them is compared with Mitsuba
EQUAL_ERRORS = (0.08, 0.04, 0.02, 0.01)
REF_PIXELS = 2048
REF_SPP = 4096
RESULTS = ROOT / "bench" / "results"


def build_scene(workers):
    import trimesh

    mesh = body_mesh()
    vertices, faces = trimesh.remesh.subdivide(mesh.vertices, mesh.faces)
    body = trimesh.Trimesh(vertices, faces, process=False)
    return Scene.from_trimesh(body, threads=workers), len(faces)


def subset_geometry(geometry, count, seed=0):
    """The same camera geometry with the mask reduced to `count` random mask pixels."""
    pixels = np.flatnonzero(geometry.mask.ravel())
    keep = np.random.default_rng(seed).choice(pixels, size=min(count, pixels.size), replace=False)
    mask = np.zeros(geometry.mask.size, bool)
    mask[keep] = True
    return replace(geometry, mask=mask.reshape(geometry.mask.shape))


def errors(result, reference):
    """(relative RMSE, median true relative error, median reported relative error) on the
    reference's pixels; relative to the channel-mean reference."""
    m = reference.mask
    ref = reference.mean[m].mean(axis=1).astype(np.float64)
    got = result.mean[m].mean(axis=1).astype(np.float64)
    rel_rmse = np.sqrt(np.mean((got - ref) ** 2)) / np.mean(ref)
    lit = ref > 1e-3 * np.median(ref)
    true_rel = np.median(np.abs(got - ref)[lit] / ref[lit])
    reported = np.median(result.relative_error()[m][lit])
    return float(rel_rmse), float(true_rel), float(reported)


def raw_embree_rate(scene, geometry, rays=2_000_000):
    """Mrays/s of bare embreex occlusion queries on cosine rays from the visible surface."""
    pixels = np.flatnonzero(geometry.mask.ravel())
    index = np.random.default_rng(1).choice(pixels, size=rays)
    p = geometry.position.reshape(-1, 3)[index].astype(np.float64)
    n = geometry.normal.reshape(-1, 3)[index].astype(np.float64)
    g = geometry.geometric_normal.reshape(-1, 3)[index].astype(np.float64)
    d = cosine_directions(n, np.random.default_rng(2).random((rays, 2)))
    origins = ray_origins(scene, p, g).astype(np.float32)
    d = d.astype(np.float32)
    rates = {}
    for threads in (1, 2):
        tracer = Scene(scene.vertices, scene.faces, threads=threads)
        tracer.warm_up()
        start = time.perf_counter()
        tracer.occluded(origins, d)
        rates[threads] = rays / (time.perf_counter() - start) / 1e6
        tracer.close()
    return rates


def same_rays_rates(scene, geometry, light, spp=64, repeats=3):
    """(integrator Mrays/s, raw embreex Mrays/s on exactly the rays it traced), one process:
    the render's occlusion batches are recorded in one render, replayed on a fresh tracer in
    the same batches, and the integrator is timed on renders that record nothing (the same
    seed traces the same rays). Medians of `repeats`."""
    batches = []
    traced = scene.occluded

    def recording(origins, directions, tmax=None):
        batches.append((np.array(origins, np.float32), np.array(directions, np.float32), tmax))
        return traced(origins, directions, tmax)

    scene.occluded = recording
    try:
        shade_environment(scene, geometry, light, spp=spp, seed=1)
    finally:
        del scene.occluded
    rays = sum(o.shape[0] for o, _, _ in batches)
    tracer = Scene(scene.vertices, scene.faces, threads=1)
    tracer.warm_up()
    ours, raw = [], []
    for _ in range(repeats):
        result = shade_environment(scene, geometry, light, spp=spp, seed=1)
        assert result.rays == rays
        ours.append(result.rays / result.seconds / 1e6)
        start = time.perf_counter()
        for origins, directions, tmax in batches:
            tracer.occluded(origins, directions, tmax)
        raw.append(rays / (time.perf_counter() - start) / 1e6)
    tracer.close()
    return float(np.median(ours)), float(np.median(raw))


def throughput(args):
    """Mrays/s of the integrator (one process, 64 spp) against raw embreex on the same rays
    and on cosine rays from the visible surface (raw_embree_rate)."""
    scene, triangles = build_scene(1)
    geometry = render_pixel_geometry(scene, default_rect(scene), (args.res, args.res))
    for hdr_name, hdr_file in HDRS.items():
        light = EnvironmentLight(load_hdr(hdr_file))
        light.sun_and_sky()
        shade_environment(scene, geometry, light, spp=8, seed=1)  # warm
        ours, raw = same_rays_rates(scene, geometry, light)
        print(f"{hdr_name}: integrator {ours:.2f} Mrays/s, raw embreex on the same rays {raw:.2f} "
              f"({ours / raw:.0%})")
    rates = raw_embree_rate(scene, geometry)
    print(f"raw embreex on cosine rays from the visible surface: {rates[1]:.2f} Mrays/s on 1 process")


def run(args):
    RESULTS.mkdir(parents=True, exist_ok=True)
    scene, triangles = build_scene(1)
    geometry = render_pixel_geometry(scene, default_rect(scene), (args.res, args.res))
    coverage = float(geometry.mask.mean())
    print(f"body: {triangles} triangles, {args.res}x{args.res}, mask covers {coverage:.1%}")
    mi = mitsuba_module() if args.mitsuba else None
    if args.mitsuba and mi is None:
        print("mitsuba (llvm_ad_rgb) unavailable: `pip install mitsuba==3.6.4` and a libLLVM")
    rows = []
    spps = [s for s in (4, 16, 64, 256, 1024) if s <= args.max_spp]
    for hdr_name, hdr_file in HDRS.items():
        light = EnvironmentLight(load_hdr(hdr_file))
        light.sun_and_sky()
        subset = subset_geometry(geometry, REF_PIXELS)
        start = time.perf_counter()
        reference = shade_environment(scene, subset, light, spp=REF_SPP, seed=12345,
                                      workers=args.workers)
        print(f"{hdr_name}: reference {REF_SPP} spp on {REF_PIXELS} pixels in "
              f"{time.perf_counter() - start:.1f} s, median rel. stderr "
              f"{reference.median_relative_error():.4f}")
        jobs = [(s, "spp", spp, None) for s in args.strategies for spp in spps]
        jobs += [("mis", "target", args.max_spp * 4, t) for t in TARGETS]
        for strategy, mode, spp, target in jobs:
            result = shade_environment(scene, geometry, light, spp=spp, target_error=target,
                                       strategy=strategy.removesuffix("-nocv"), seed=1,
                                       workers=args.workers,
                                       control_variate=not strategy.endswith("-nocv"))
            rel_rmse, true_rel, reported = errors(result, reference)
            row = dict(hdr=hdr_name, strategy=strategy, plan=result.strategy, mode=mode,
                       spp=float(result.passes[geometry.mask].mean()), target=target or "",
                       seconds=round(result.seconds, 3), rays=result.rays,
                       mrays_per_s=round(result.rays / result.seconds / 1e6, 3),
                       rel_rmse=round(rel_rmse, 5), median_rel_error=round(true_rel, 5),
                       median_rel_error_reported=round(reported, 5), workers=args.workers,
                       coverage=round(coverage, 4))
            rows.append(row)
            print_row(row)
        if mi is not None:
            rows += mitsuba_rows(mi, scene, geometry, load_hdr(hdr_file), hdr_name,
                                 [s for s in (4, 16, 64, 256, 1024, 4096) if s <= args.mitsuba_max_spp],
                                 coverage)
            print_equal_error_ratios(rows, hdr_name)
    write_csv(rows)
    plot(rows)
    rates = raw_embree_rate(scene, geometry)
    print(f"raw embreex occlusion: {rates[1]:.2f} Mrays/s on 1 process, {rates[2]:.2f} on 2 "
          f"({rates[2] / rates[1]:.2f}x)")
    scaling(scene, geometry, args)


def print_row(row):
    print(f"{row['hdr']:9s} {row['strategy']:8s} {row['plan']:8s} {row['mode']:6s} spp {row['spp']:7.1f} "
          f"target {str(row['target'] or '-'):5s} {row['seconds']:8.2f} s  {row['mrays_per_s']:6.2f} Mrays/s  "
          f"relRMSE {row['rel_rmse']:.4f}  median rel err {row['median_rel_error']:.4f} "
          f"(reported {row['median_rel_error_reported']:.4f})")


# ---------------------------------------------------------------------------- Mitsuba 3
def mitsuba_module():
    """mitsuba with its LLVM variant, or None (a bench-only tool, never a runtime dependency)."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = sorted(glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM*.so*"), reverse=True)
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    try:
        import mitsuba
    except ImportError:
        return None
    try:
        mitsuba.set_variant("llvm_ad_rgb")
    except (ImportError, AttributeError, RuntimeError):
        return None
    return mitsuba


class MitsubaJob:
    """Mitsuba's own renderer on the same job: our mesh (PLY with our vertex normals) and map
    (the same texels; Mitsuba reads them bilinearly, we as constants), a white diffuse BSDF,
    its `direct` integrator (MIS), an orthographic sensor over our rectangle looking along -Z,
    a RES x RES film, `mi.render` with spp samples per pixel. Its relative RMSE over our
    masked pixels comes from two independent renders: RMSE^2 = mean((a - b)^2) / 2."""

    def __init__(self, mi, scene, geometry, env):
        import tempfile

        import trimesh
        from test_mitsuba import to_mitsuba_bitmap

        mesh = trimesh.Trimesh(scene.to_world(scene.vertices), scene.faces,
                               vertex_normals=scene.vertex_normals, process=False)
        x0, x1, y0, y1 = (float(v) for v in geometry.rect)
        height, width = geometry.mask.shape
        top = float(mesh.bounds[1, 2] + 0.01 * np.linalg.norm(mesh.extents))
        centre = [(x0 + x1) / 2, (y0 + y1) / 2]
        transform = mi.ScalarTransform4f
        to_world = (transform().look_at(origin=centre + [top], target=centre + [top - 1.0], up=[0, 1, 0])
                    @ transform().scale([(x1 - x0) / 2, (y1 - y0) / 2, 1.0]))
        with tempfile.TemporaryDirectory() as folder:
            path = os.path.join(folder, "mesh.ply")
            mesh.export(path, vertex_normal=True)
            self.scene = mi.load_dict({
                "type": "scene", "integrator": {"type": "direct"},
                "env": {"type": "envmap", "bitmap": mi.Bitmap(to_mitsuba_bitmap(env))},
                "mesh": {"type": "ply", "filename": path, "bsdf": {
                    "type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}},
                "sensor": {"type": "orthographic", "to_world": to_world,
                           "film": {"type": "hdrfilm", "width": width, "height": height,
                                    "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                           "sampler": {"type": "independent", "sample_count": 1}},
            })
        self.mask = geometry.mask
        self.mi = mi

    def render(self, spp, seed=0):
        """(channel-mean image (H, W) float64, seconds) of one render at spp samples per pixel."""
        start = time.perf_counter()
        image = np.array(self.mi.render(self.scene, spp=spp, seed=seed))
        return image.mean(axis=2).astype(np.float64), time.perf_counter() - start


def mitsuba_rows(mi, scene, geometry, env, hdr_name, spps, coverage):
    """Mitsuba's error against run time on the same job: rows like ours (strategy "mitsuba"),
    its relative RMSE on our masked pixels from two independent renders (see MitsubaJob);
    the time is their mean."""
    job = MitsubaJob(mi, scene, geometry, env)
    job.render(4, seed=99)  # compiles its kernels
    rows = []
    for spp in spps:
        (a, seconds_a), (b, seconds_b) = job.render(spp, seed=2 * spp), job.render(spp, seed=2 * spp + 1)
        a, b = a[job.mask], b[job.mask]
        rel_rmse = float(np.sqrt(np.mean((a - b) ** 2) / 2) / np.mean((a + b) / 2))
        seconds = (seconds_a + seconds_b) / 2
        row = dict(hdr=hdr_name, strategy="mitsuba", plan="direct", mode="spp", spp=float(spp),
                   target="", seconds=round(seconds, 3), rays="", mrays_per_s="",
                   rel_rmse=round(rel_rmse, 5), median_rel_error="",
                   median_rel_error_reported="", workers="all", coverage=round(coverage, 4))
        rows.append(row)
        print(f"{hdr_name:9s} mitsuba  direct   spp    spp {spp:7.1f}               {seconds:8.2f} s"
              f"                   relRMSE {rel_rmse:.4f} (two independent renders)")
    return rows


def time_at_error(points, error):
    """Seconds at which a sweep [(seconds, rel_rmse), ...] reaches `error`, interpolated
    log-log between the two runs that bracket it; None outside the sweep."""
    points = sorted(points)
    for (t0, e0), (t1, e1) in zip(points, points[1:]):
        if e0 >= error >= e1 and e0 > e1:
            f = np.log(e0 / error) / np.log(e0 / e1)
            return float(np.exp(np.log(t0) + f * np.log(t1 / t0)))
    return None


def print_equal_error_ratios(rows, hdr_name):
    """Time to equal error, ours (the planned default "mis") over Mitsuba, same run."""
    def sweep(strategy):
        return [(r["seconds"], r["rel_rmse"]) for r in rows
                if r["hdr"] == hdr_name and r["strategy"] == strategy and r["mode"] == "spp"]

    for error in EQUAL_ERRORS:
        ours, theirs = time_at_error(sweep("mis"), error), time_at_error(sweep("mitsuba"), error)
        if ours is None or theirs is None:
            print(f"{hdr_name}: relative RMSE {error}: outside a sweep (ours {ours}, Mitsuba {theirs})")
            continue
        print(f"{hdr_name}: relative RMSE {error}: ours {ours:.3f} s, Mitsuba {theirs:.3f} s, "
              f"ratio {ours / theirs:.2f}")


def scaling(scene, geometry, args, repeats=3):
    """Integrator wall time on 1 and 2 worker processes, same render, median of `repeats`;
    and, because a shared machine makes wall-clock scaling meaningless, the scaling two idle
    cores would give from measured CPU times: the calling process samples one share and
    merges, the forked worker samples the other, so the busier of the two sets the time."""
    import resource

    light = EnvironmentLight(load_hdr(HDRS["hard_sun"]))
    light.sun_and_sky()
    walls, ideals = {}, {}
    for workers in (1, 2):
        runs = []
        for _ in range(repeats):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            parent = time.process_time()
            result = shade_environment(scene, geometry, light, spp=64, seed=1, workers=workers)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            parent = time.process_time() - parent
            children = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            # the calling process samples a share too: the slower process sets the time
            ideal = parent if workers == 1 else max(parent, children / (workers - 1))
            runs.append((result.seconds, ideal, parent, children, result.rays / result.seconds / 1e6))
        wall, ideal, parent, children, rate = (float(np.median(c)) for c in zip(*runs))
        walls[workers], ideals[workers] = wall, ideal
        print(f"integrator, {workers} worker(s): {wall:.2f} s wall (median of {repeats}), "
              f"{rate:.2f} Mrays/s, CPU: calling process {parent:.2f} s, workers {children:.2f} s, "
              f"on idle cores (from CPU times) {ideal:.2f} s")
    print(f"integrator scaling 1 -> 2 workers: wall clock {walls[1] / walls[2]:.2f}x, "
          f"on idle cores (from CPU times) {ideals[1] / ideals[2]:.2f}x")


def headline(args):
    """The issue's target: 512x512, hard sun, median pixel relative error <= 2% in <= 1 s.
    Reports what a 1.0 s time budget reaches, and the time the 2% target takes."""
    scene, triangles = build_scene(1)
    geometry = render_pixel_geometry(scene, default_rect(scene), (args.res, args.res))
    # The frame is filled ~30% by the body; this body fills 27% of its own bounding
    # box. Cost and error are per masked pixel, so render the same framing at the resolution
    # that gives as many masked pixels as args.res^2 x args.coverage.
    side = int(round(args.res * np.sqrt(args.coverage / geometry.mask.mean())))
    geometry = render_pixel_geometry(scene, default_rect(scene), (side, side))
    light = EnvironmentLight(load_hdr(HDRS["hard_sun"]))
    start = time.perf_counter()
    light.sun_and_sky()
    print(f"{triangles} triangles, {side}x{side}, mask {geometry.mask.mean():.1%} = "
          f"{int(geometry.mask.sum())} pixels ({geometry.mask.sum() / args.res**2:.1%} of "
          f"{args.res}x{args.res}); environment distributions built in {time.perf_counter() - start:.2f} s")
    subset = subset_geometry(geometry, REF_PIXELS)
    reference = shade_environment(scene, subset, light, spp=REF_SPP, seed=12345, workers=args.workers)
    for label, options in (("time budget 1.0 s", dict(time_budget=1.0, spp=1 << 16)),
                           ("target error 0.02", dict(target_error=0.02, spp=4096)),
                           ("64 spp", dict(spp=64))):
        result = shade_environment(scene, geometry, light, seed=1, workers=args.workers, **options)
        rel_rmse, true_rel, reported = errors(result, reference)
        print(f"{label:18s}: {result.seconds:6.2f} s, {result.passes[geometry.mask].mean():6.1f} spp, "
              f"median rel. error {true_rel:.4f} (reported {reported:.4f}), rel. RMSE {rel_rmse:.4f}, "
              f"{result.rays / result.seconds / 1e6:.2f} Mrays/s")
    scaling(scene, geometry, args)


def write_csv(rows):
    path = RESULTS / "integrator_error_vs_time.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")


def plot(rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(HDRS), figsize=(11, 4.5), sharey=True)
    for ax, hdr in zip(axes, HDRS):
        for strategy in STRATEGIES + ("mitsuba",):
            pts = [(r["seconds"], r["rel_rmse"]) for r in rows
                   if r["hdr"] == hdr and r["strategy"] == strategy and r["mode"] == "spp"]
            if pts:
                ax.loglog(*zip(*pts), "s--" if strategy == "mitsuba" else "o-",
                          label="Mitsuba 3 (direct)" if strategy == "mitsuba" else strategy)
        pts = [(r["seconds"], r["rel_rmse"]) for r in rows if r["hdr"] == hdr and r["mode"] == "target"]
        if pts:
            ax.loglog(*zip(*pts), "k*", markersize=10, label="mis, target error")
        ax.set_title(f"{hdr} ({HDRS[hdr]})")
        ax.set_xlabel("wall time [s]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("relative RMSE vs reference")
    axes[0].legend()
    fig.tight_layout()
    path = RESULTS / "integrator_error_vs_time.png"
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--res", type=int, default=512)
    parser.add_argument("--max-spp", type=int, default=1024)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="128x128, up to 64 spp")
    parser.add_argument("--strategies", default=",".join(STRATEGIES),
                        help="comma-separated subset of " + ", ".join(STRATEGIES))
    parser.add_argument("--mitsuba", action="store_true",
                        help="add Mitsuba 3 on the same job and print time-to-equal-error ratios")
    parser.add_argument("--mitsuba-max-spp", type=int, default=1024)
    parser.add_argument("--coverage", type=float, default=0.30,
                        help="--headline: as many masked pixels as this share of --res x --res")
    parser.add_argument("--headline", action="store_true",
                        help="only the 1 s / 2%% target on the hard sun, and the scaling")
    parser.add_argument("--throughput", action="store_true",
                        help="only Mrays/s against raw embreex on the same rays (one process)")
    args = parser.parse_args()
    args.strategies = tuple(args.strategies.split(","))
    if args.quick:
        args.res, args.max_spp = 128, 64
    if args.headline:
        headline(args)
    elif args.throughput:
        throughput(args)
    else:
        run(args)


if __name__ == "__main__":
    main()
