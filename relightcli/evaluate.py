"""`relight eval`: the paper's Table 1 protocol on scene folders with ground truth.

A scene folder holds `input.png` (8-bit sRGB photo under lighting A), `target.hdr` (lighting B),
`gt_mask.png`, `gt_albedo.exr`, `gt_shading.exr` (under B), `gt_relit.exr` (under B) and
optionally `gt_normal.exr`; EXRs are linear. Metrics over the ground-truth foreground mask: MSE
(reported x1e3), SSIM (Gaussian window 11, sigma 1.5, per channel, averaged over the mask) and
PSNR, on sRGB-encoded values clipped to [0, 1]. Shading is first divided, prediction and ground
truth alike, by one per-scene constant: the 95th percentile of the ground-truth shading over the
mask (RGB pooled) divided by 0.8, so that bright shading is not hidden by the clip. With
`gt_normal.exr`, also the mean angle between the predicted (the geometry stage's, camera frame)
and the true normals over the mask. Relit, albedo and shading are scored as the product gives
them: straight layers times the mask (the predicted one, or the true one with --use-gt-mask)
once, the relit person over black (`relight --background '#000000'`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from relightcli import metrics
from relightcli.errors import InputError, RelightError, UsageError
from relightcli.io.images import linear_to_srgb, read_image

LAYERS = ("relit", "albedo", "shading")
REQUIRED_FILES = ("input.png", "target.hdr", "gt_mask.png", "gt_albedo.exr", "gt_shading.exr", "gt_relit.exr")
SHADING_PERCENTILE, SHADING_TARGET = 95.0, 0.8
PSNR_CAP = 100.0  # dB: identical images have infinite PSNR, which JSON cannot carry

# The paper's Table 1 (test set, foreground only): (MSE x1e3, SSIM, PSNR) per layer.
PAPER_TABLE = {
    "RH (SH-9), retrained": {"relit": (3.781, 0.9506, 26.45), "albedo": (2.819, 0.9559, 26.73), "shading": (8.333, 0.9236, 22.39)},
    "SFHR (SH-25)": {"relit": (5.833, 0.9349, 24.66), "albedo": (4.185, 0.9613, 24.98), "shading": (12.79, 0.9155, 21.41)},
    "paper": {"relit": (1.311, 0.9638, 30.20), "albedo": (1.468, 0.9814, 30.27), "shading": (0.729, 0.9626, 32.86)},
}


@dataclass
class Scene:
    """Ground truth of one scene; images (H, W, 3) float32 linear, mask (H, W) in [0, 1]."""

    name: str
    folder: Path
    mask: np.ndarray
    albedo: np.ndarray
    shading: np.ndarray
    relit: np.ndarray
    normal: np.ndarray | None

    @property
    def input_path(self) -> Path:
        return self.folder / "input.png"

    @property
    def target_path(self) -> Path:
        return self.folder / "target.hdr"


def find_scenes(dataset: str | Path) -> list[Path]:
    """Scene folders below `dataset` (the folder itself when it is one), sorted."""
    root = Path(dataset)
    if not root.is_dir():
        raise InputError("not a folder", path=root, fix="pass a folder of scene folders")
    candidates = [root] if (root / "input.png").exists() else sorted(p for p in root.iterdir() if p.is_dir())
    scenes = [p for p in candidates if (p / "input.png").exists()]
    if not scenes:
        raise UsageError(f"no scene folders (with input.png) in {root}", fix="see `relight eval --help` for the layout")
    return scenes


def load_scene(folder: str | Path) -> Scene:
    folder = Path(folder)
    missing = [name for name in REQUIRED_FILES if not (folder / name).is_file()]
    if missing:
        raise InputError(f"scene is missing {', '.join(missing)}", path=folder,
                         fix=f"a scene folder holds {', '.join(REQUIRED_FILES)}")
    mask = read_image(folder / "gt_mask.png", srgb=False).rgb[..., 0]
    normal = read_image(folder / "gt_normal.exr").rgb if (folder / "gt_normal.exr").is_file() else None
    scene = Scene(folder.name, folder, mask, read_image(folder / "gt_albedo.exr").rgb,
                  read_image(folder / "gt_shading.exr").rgb, read_image(folder / "gt_relit.exr").rgb, normal)
    for name in ("albedo", "shading", "relit", "normal"):
        truth = getattr(scene, name)
        if truth is None:
            continue
        if truth.shape[:2] != mask.shape:
            raise InputError(f"gt_{name}.exr is not the size of gt_mask.png", path=folder, fix="regenerate the scene")
        if not np.isfinite(truth).all():
            raise InputError(f"gt_{name}.exr holds NaN or Inf values", path=folder, fix="regenerate the scene")
    return scene


def shading_normaliser(gt_shading: np.ndarray, mask: np.ndarray) -> float:
    """The per-scene constant both shadings are divided by (see the module docstring)."""
    values = gt_shading[mask > 0.5]
    p = float(np.percentile(values, SHADING_PERCENTILE)) if values.size else 0.0
    return p / SHADING_TARGET if p > 0 else 1.0


def layer_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    """MSE x1e3, SSIM, PSNR of two linear images over the mask, sRGB-encoded and clipped."""
    a = linear_to_srgb(np.clip(np.nan_to_num(pred), 0.0, 1.0))
    b = linear_to_srgb(np.clip(gt, 0.0, 1.0))
    psnr = min(metrics.psnr(a, b, mask), PSNR_CAP)
    return {"mse": metrics.mse(a, b, mask) * 1e3, "ssim": metrics.ssim(a, b, mask), "psnr": psnr}


def scene_metrics(scene: Scene, pred: dict[str, np.ndarray]) -> dict:
    """pred: 'relit', 'albedo', 'shading', each (H, W, 3) float32 linear, full frame."""
    scale = shading_normaliser(scene.shading, scene.mask)
    out = {}
    for layer in LAYERS:
        if pred[layer].shape != getattr(scene, layer).shape:
            raise RelightError(f"predicted {layer} is {pred[layer].shape}, ground truth {getattr(scene, layer).shape}")
        p, g = pred[layer], getattr(scene, layer)
        if layer == "shading":
            p, g = p / scale, g / scale
        out[layer] = layer_metrics(p, g, scene.mask)
    if scene.normal is not None and pred.get("normal") is not None:
        out["normal"] = normal_metrics(pred["normal"], scene.normal, scene.mask)
    return out


def normal_metrics(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """Mean angle in degrees between predicted and true (H, W, 3) normals over the true mask's
    pixels (> 0.5) that both give a normal; `covered`: their share of the mask."""
    inside = (mask > 0.5) & (np.linalg.norm(pred, axis=-1) > 1e-6) & (np.linalg.norm(truth, axis=-1) > 1e-6)
    share = float(inside.sum() / max(int((mask > 0.5).sum()), 1))
    if not inside.any():
        return {"deg": None, "covered": share}
    p, t = pred[inside], truth[inside]
    cosine = np.sum(p * t, -1) / (np.linalg.norm(p, axis=-1) * np.linalg.norm(t, axis=-1))
    return {"deg": float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))).mean()), "covered": share}


def evaluate(scene_folders: list[Path], predict: Callable[[Scene], dict], method: str,
             on_done: Callable[[dict], None] | None = None) -> dict:
    """Run `predict` on every scene and average the metrics over the scenes that succeeded.
    A scene that fails is reported with its error; the others still count."""
    per_scene = []
    for folder in scene_folders:
        entry = {"scene": folder.name, "error": None}
        start = time.perf_counter()
        try:
            scene = load_scene(folder)
            entry.update(scene_metrics(scene, predict(scene)))
        except RelightError as exc:
            entry["error"] = str(exc)
            entry["exit_code"] = exc.exit_code
        entry["seconds"] = round(time.perf_counter() - start, 4)
        per_scene.append(entry)
        if on_done is not None:
            on_done(entry)
    ok = [e for e in per_scene if e["error"] is None]
    result = {"method": method, "scenes": len(ok), "failed": len(per_scene) - len(ok),
              "seconds_per_image": float(np.mean([e["seconds"] for e in ok])) if ok else None}
    for layer in LAYERS:
        result[layer] = {k: float(np.mean([e[layer][k] for e in ok])) if ok else None for k in ("mse", "ssim", "psnr")}
    angles = [e["normal"]["deg"] for e in ok if e.get("normal", {}).get("deg") is not None]
    if angles:
        result["normal"] = {"deg": float(np.mean(angles)), "scenes": len(angles)}
    result["per_scene"] = per_scene
    return result


def finite_json(value):
    """`value` (dicts, lists, numbers) with every NaN or infinite float made None: what
    json.dumps writes is then JSON (it writes NaN, which JSON has not)."""
    if isinstance(value, dict):
        return {key: finite_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(item) for item in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def format_table(result: dict) -> str:
    """The paper's Table 1 layout with our row appended: MSE x1e3 / SSIM / PSNR per layer."""
    header = f"{'method':<24} | {'relight':^24} | {'albedo':^24} | {'shading':^24}"
    lines = [header, "-" * len(header)]
    for name, row in PAPER_TABLE.items():
        cells = [" / ".join(f"{v:.4g}" for v in row[layer]) for layer in LAYERS]
        lines.append(f"{name:<24} | " + " | ".join(f"{c:^24}" for c in cells))
    ours = []
    for layer in LAYERS:
        values = result[layer]
        ours.append("n/a" if values["mse"] is None else f"{values['mse']:.4g} / {values['ssim']:.4f} / {values['psnr']:.2f}")
    name = result["method"] + (", net albedo" if result.get("albedo_source") == "net" else "")
    lines.append(f"{'ours: ' + name:<24} | " + " | ".join(f"{c:^24}" for c in ours))
    lines.append(f"{result['scenes']} scenes, {result['failed']} failed")
    if "normal" in result:
        lines.append(f"normals: {result['normal']['deg']:.2f} deg mean angular error "
                     f"({result['normal']['scenes']} scenes with true normals)")
    return "\n".join(lines)
