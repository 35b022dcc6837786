"""True error of the traced visibility before and after the adaptive Wiener filter
(relightcli.render.denoise), against a converged reference (not part of the test suite).

    python bench/bench_denoise.py [--res 256] [--spp 8,16,32,64] [--ref-spp 1024] [--maps a.hdr,...]

The integrator bench's body (MakeHuman, subdivided once) at RES x RES, shadow rays lifted as
the pipeline's (stages.shading.SHADOW_LIFT), under each map: the shading at each sample count, as
rendered and with its visibility (traced / unoccluded shading) filtered with the
integrator's own per-pixel error (render.denoise.filtered_shading, as stages.shading.traced does), against REF_SPP samples on
every masked pixel. Prints relative RMSE, the share of pixels more than 50% off the
reference, the median error the integrator reports (before filtering) and the time of the
render and of the filter; writes bench/results/denoise.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "render"))

from render_testing import body_mesh, load_hdr  # noqa: E402

from relightcli.render.camera import default_rect, render_pixel_geometry  # noqa: E402
from relightcli.render.denoise import filtered_shading  # noqa: E402
from relightcli.render.environment import EnvironmentLight  # noqa: E402
from relightcli.render.integrator import shade_environment  # noqa: E402
from relightcli.render.scene import Scene  # noqa: E402
from relightcli.stages.shading import SHADOW_LIFT  # noqa: E402

MAPS = ("noon_grass_1k.hdr", "kloofendal_overcast_1k.hdr", "brown_photostudio_02_1k.hdr",
        "autoshop_01_1k.hdr", "circus_arena_1k.hdr")


def errors(mean, reference, mask):
    """(relative RMSE, share of pixels more than 50% off) on the channel mean over mask."""
    got, ref = mean[mask].mean(axis=1), reference[mask].mean(axis=1)
    rmse = float(np.sqrt(np.mean((got - ref) ** 2)) / ref.mean())
    return rmse, float(np.mean(np.abs(got - ref) > 0.5 * np.maximum(ref, 1e-12)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--spp", default="8,16,32,64")
    parser.add_argument("--ref-spp", type=int, default=1024)
    parser.add_argument("--maps", default=",".join(MAPS))
    args = parser.parse_args()
    import trimesh

    mesh = body_mesh()
    scene = Scene(*trimesh.remesh.subdivide(mesh.vertices, mesh.faces))
    geometry = render_pixel_geometry(scene, default_rect(scene), (args.res, args.res))
    rows = []
    for name in args.maps.split(","):
        light = EnvironmentLight(load_hdr(name))
        reference = shade_environment(scene, geometry, light, spp=args.ref_spp, seed=7, lift=SHADOW_LIFT).mean
        for spp in (int(s) for s in args.spp.split(",")):
            result = shade_environment(scene, geometry, light, spp=spp, seed=1, lift=SHADOW_LIFT)
            start = time.perf_counter()
            mean = filtered_shading(result, light, geometry.normal)
            seconds = time.perf_counter() - start
            raw, off = errors(result.mean, reference, geometry.mask)
            after, off_after = errors(mean, reference, geometry.mask)
            row = {"map": name, "spp": spp, "render_s": round(result.seconds, 3), "filter_s": round(seconds, 4),
                   "rel_rmse": round(raw, 4), "rel_rmse_filtered": round(after, 4),
                   "off_50pct": round(off, 4), "off_50pct_filtered": round(off_after, 4),
                   "reported_median": round(result.median_relative_error(), 4)}
            rows.append(row)
            print(f"{name:30s} {spp:4d} spp {result.seconds:6.2f} s (+{seconds * 1e3:.0f} ms): relative RMSE "
                  f"{raw:.4f} -> {after:.4f}, >50% off {off:.4f} -> {off_after:.4f}, reported median "
                  f"{row['reported_median']:.4f}", flush=True)
    out = ROOT / "bench" / "results" / "denoise.json"
    out.write_text(json.dumps({"res": args.res, "ref_spp": args.ref_spp, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
