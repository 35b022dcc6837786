"""Write a dataset split as `relight eval` scene folders (relightcli/evaluate.py):
`python -m export.factory.eval_scenes DATASET OUT [--split test] [--limit N]`.

Per sample, OUT/<split>_<id>/ holds input.png (the stored 8-bit sRGB photo under lighting A,
byte for byte), target.hdr (lighting B in the camera frame, full resolution, times B's
energy gain and the photo's exposure, so it is the light that gt_shading.exr was rendered
under), gt_mask.png (8-bit, no transfer curve), gt_albedo.exr, gt_shading.exr (under B),
gt_relit.exr (under B), gt_normal.exr (EXRs linear, float16), and scene.json (the metadata).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from relightcli.errors import RelightError
from relightcli.io.images import write_image

from . import dataset, lighting


def target_environment(meta: dict, hdri_folder: str | None = None) -> np.ndarray:
    """(H, 2H, 3) float32 linear radiance: lighting B of a sample as its shading saw it."""
    spec = meta["spec"]
    light_b = lighting.LightingSpec(**spec["lighting_b"])
    env = lighting.camera_environment(light_b, spec["pitch_deg"], spec["yaw_deg"], hdri_folder)
    return (env * np.float32(meta["lighting_b_gain"] * meta["exposure"])).astype(np.float32)


def _write_png_bytes(path: Path, rgb_u8) -> None:
    """The uint8 sRGB photo as PNG, byte for byte (OpenCV wants BGR)."""
    temporary = path.with_name(f".{path.name}.tmp.png")
    if not cv2.imwrite(str(temporary), np.ascontiguousarray(rgb_u8[..., ::-1])):
        raise RelightError("cannot write PNG", path=path, fix="check free disk space")
    temporary.replace(path)


def write_scene(data: dataset.Dataset, split: str, sample_id: str, out_dir) -> Path:
    """One scene folder OUT/<split>_<id>; returns its path."""
    folder = Path(out_dir) / f"{split}_{sample_id}"
    folder.mkdir(parents=True, exist_ok=True)
    arrays, meta = data.load(split, sample_id), data.meta(split, sample_id)
    _write_png_bytes(folder / "input.png", data.load_raw(split, sample_id, "input"))
    folder_hdri = meta.get("settings", {}).get("hdri_folder")
    write_image(folder / "target.hdr", target_environment(meta, folder_hdri))
    write_image(folder / "gt_mask.png", arrays["mask"], srgb=False)
    for name, key in (("gt_albedo", "albedo"), ("gt_shading", "shading_b"),
                      ("gt_relit", "relit_b"), ("gt_normal", "normal")):
        write_image(folder / f"{name}.exr", arrays[key])
    (folder / "scene.json").write_text(json.dumps(meta, indent=2, sort_keys=True))
    return folder


def write_eval_scenes(root, out_dir, split: str = "test", limit: int | None = None) -> list[Path]:
    """Scene folders for the first `limit` samples (all when None) of a split."""
    data = dataset.open_dataset(root)
    ids = data.ids(split)[:limit]
    return [write_scene(data, split, sample_id, out_dir) for sample_id in ids]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.factory.eval_scenes",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("out")
    parser.add_argument("--split", default="test", choices=dataset.SPLITS)
    parser.add_argument("--limit", type=int, default=None)
    args = parser.parse_args(argv)
    try:
        folders = write_eval_scenes(args.dataset, args.out, args.split, args.limit)
    except RelightError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    print(f"wrote {len(folders)} scene folders to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
