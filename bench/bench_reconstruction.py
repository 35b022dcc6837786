"""Reconstruction from the shipped geometry net against ground-truth geometry, on the data
factory's test split (issue "Single-image 3D reconstruction"): depth error on the mask, Chamfer
distance, and what matters, the shading PSNR of the ray-traced shading on the reconstructed
mesh against the shading on the ground-truth mesh under the same environment.

    python bench/bench_reconstruction.py [--data data/factory256] [--count 30] [--spp 32]

The true mask is used (this measures geometry, not the mask). Depth is compared in the net's
translation-invariant units (export.train.data.relative_depths: the crop spans [-1, 1] in X,
mean front depth 0), reported in pixels of the crop. Variants: the runtime's reconstruction
(depth smoothed inside the person, then 10 cotangent steps) and the paper's 10 steps alone. The
ground-truth mesh is built from the ground-truth depth the same way, without smoothing. Writes
bench/results/reconstruction.json.
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

from export.factory.dataset import open_dataset  # noqa: E402
from export.train.data import relative_depths  # noqa: E402
from relightcli.evaluate import layer_metrics, shading_normaliser  # noqa: E402
from relightcli.geometry.mesh import reconstruct_mesh  # noqa: E402
from relightcli.geometry.smoothing import DEPTH_SIGMA, smooth_depth, smooth_mesh  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.nets.geometry import GeometryNet  # noqa: E402
from relightcli.render import EnvironmentLight, Scene, render_pixel_geometry, shade_environment  # noqa: E402

HDRS = {"hard_sun": "noon_grass_1k.hdr", "overcast": "kloofendal_overcast_1k.hdr"}
RECT = (-1.0, 1.0, -1.0, 1.0)


def meshes(mask, front_pred, back_pred, front_gt, back_gt):
    """{variant: trimesh} for the prediction (runtime and paper-only smoothing) and the truth."""
    sigma = DEPTH_SIGMA * mask.shape[0]
    front_s = smooth_depth(front_pred, mask, sigma)
    back_s = np.minimum(smooth_depth(back_pred, mask, sigma), front_s)
    return {
        "runtime": smooth_mesh(reconstruct_mesh(mask, front_s, back_s, RECT).to_trimesh()),
        "paper_steps_only": smooth_mesh(reconstruct_mesh(mask, front_pred, np.minimum(back_pred, front_pred), RECT).to_trimesh()),
        "truth": reconstruct_mesh(mask, front_gt, np.minimum(back_gt, front_gt), RECT),
    }


def chamfer(a, b, count=20000, seed=0):
    """Symmetric mean nearest-surface-point distance between two meshes (their units)."""
    from scipy.spatial import cKDTree

    import trimesh

    pa = trimesh.sample.sample_surface(a, count, seed=seed)[0]
    pb = trimesh.sample.sample_surface(b, count, seed=seed + 1)[0]
    return 0.5 * (cKDTree(pb).query(pa)[0].mean() + cKDTree(pa).query(pb)[0].mean())


def shading(mesh, size, light, spp):
    with Scene.from_trimesh(mesh) as scene:
        hits = render_pixel_geometry(scene, RECT, (size, size))
        return shade_environment(scene, hits, light, spp=spp, seed=0).mean


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(ROOT / "data" / "factory256"))
    parser.add_argument("--count", type=int, default=30)
    parser.add_argument("--spp", type=int, default=32)
    args = parser.parse_args()
    dataset = open_dataset(args.data)
    net = GeometryNet(threads=2)
    lights = {name: EnvironmentLight(load_envmap(ROOT.parent / "shared" / "data" / "hdri" / f))
              for name, f in HDRS.items()}
    rows = []
    start = time.perf_counter()
    for sample_id in dataset.ids("test")[: args.count]:
        sample = dataset.load("test", sample_id)
        mask = sample["mask"] > 0.5
        size = mask.shape[0]
        px = size / 2.0  # crop units -> pixels
        front_gt, back_gt = relative_depths(sample)
        maps = net.predict(sample["input"])
        offset = float(maps.front_depth[mask].mean())
        front_pred, back_pred = maps.front_depth - offset, maps.back_depth - offset
        row = {"id": sample_id,
               "front_depth_error_px": float(np.abs(front_pred - front_gt)[mask].mean() * px),
               "back_depth_error_px": float(np.abs(back_pred - back_gt)[mask].mean() * px)}
        built = meshes(mask, front_pred, back_pred, front_gt, back_gt)
        truth_shading = {name: shading(built["truth"], size, light, args.spp) for name, light in lights.items()}
        for variant in ("runtime", "paper_steps_only"):
            row[f"chamfer_px_{variant}"] = float(chamfer(built[variant], built["truth"]) * px)
            for name, light in lights.items():
                gt = truth_shading[name]
                k = shading_normaliser(gt, mask)
                pred = shading(built[variant], size, light, args.spp)
                row[f"shading_psnr_{variant}_{name}"] = layer_metrics(pred / k, gt / k, mask)["psnr"]
        rows.append(row)
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    keys = [k for k in rows[0] if k != "id"]
    summary = {"samples": len(rows), "spp": args.spp, "seconds": round(time.perf_counter() - start, 1),
               "mean": {k: float(np.mean([r[k] for r in rows])) for k in keys},
               "median": {k: float(np.median([r[k] for r in rows])) for k in keys}}
    out = ROOT / "bench" / "results" / "reconstruction.json"
    out.write_text(json.dumps({"summary": summary, "samples": rows}, indent=2) + "\n")
    print(json.dumps(summary["mean"], indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
