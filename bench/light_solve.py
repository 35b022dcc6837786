"""The input light and the albedo of each `--albedo` source against the truth (issue 20).

    python bench/light_solve.py data/evalval512 data/factory512val --split val [--use-gt-mask]
    python bench/light_solve.py data/eval512 data/factory512test --split test [--use-gt-mask]

Runs the pipeline (`--method raytrace-norefine`) on every scene folder with `--albedo ratio`
(the de-lighting net's light) and `--albedo solve` (the light by inverse rendering on the
mesh), and compares with the factory's true input light (`light_a`, in the photo's exposure
units): solid-angle weighted RMS of log luminance (the truth's mean radiance / 100 added to
both, so black texels stay finite), the level ratio (mean luminance over the sphere, estimate /
truth) and the luminance correlation over the texels. Albedo and relit PSNR by the eval
protocol (relightcli.evaluate), as is and with an oracle per-channel gain on the albedo (the
gain that gives it the true albedo's mean over the person), so level and shape errors are seen
apart; the seconds of the de-lighting stage. Writes --out (JSON) and prints a table.

    RELIGHT_MODELS_DIR=DIR python bench/light_solve.py ... --sources solve solve-level-from --level-from models

scores DIR's de-lighting net with its own level and with the albedo's level from another
folder's net (here the shipped one): one net's shape, the other's level. `--delight-once`: the
de-lighting nets run on the photo alone (the stage averages the photo's and its mirror's).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from export.factory import dataset  # noqa: E402
from relightcli import compose  # noqa: E402
from relightcli.batch import ItemReport  # noqa: E402
from relightcli.evaluate import find_scenes, layer_metrics, load_scene  # noqa: E402
from relightcli.io.envmap import load_envmap, texel_directions, texel_solid_angles  # noqa: E402
from relightcli.io.images import read_image  # noqa: E402
from relightcli.nets.delight import DelightNet  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.render.sh import project_sh  # noqa: E402
from relightcli.stages import delight  # noqa: E402
from relightcli.stages.delight import SOLVE_CLIPPED  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

SOURCES = ("ratio", "solve")
# The truth in place of one quantity (substituted)
ORACLES = ("true-light", "true-light-own-level")
# The solve with the albedo's level from another models folder's de-lighting net (--level-from):
# one net's albedo shape, another's level
LEVEL_FROM = "solve-level-from"


def light_errors(estimate: np.ndarray, truth: np.ndarray) -> dict:
    """Two (16, 32, 3) lights compared: log-L2, level (mean luminance over the sphere, estimate
    / truth: the light's energy), correlation over the texels, the angle between their dominant
    directions (each the luminance-weighted mean of the texel directions) and the relative
    error of their SH bands 1-2 (luminance, each light divided by its own band 0: the shape of
    the low frequencies a person shows, level apart)."""
    omega = texel_solid_angles(*truth.shape[:2])
    a, b = estimate @ compose.LUMINANCE, truth @ compose.LUMINANCE
    floor = 0.01 * float((b * omega).sum() / omega.sum())
    log_l2 = np.sqrt((omega * (np.log(a + floor) - np.log(b + floor)) ** 2).sum() / omega.sum())
    level = float((a * omega).sum() / max((b * omega).sum(), 1e-30))
    spread = a.std() * b.std()
    correlation = float(((a - a.mean()) * (b - b.mean())).mean() / spread) if spread > 0 else 0.0
    directions = texel_directions(*truth.shape[:2]).reshape(-1, 3)
    pulls = [directions.T @ (x * omega).ravel() for x in (a, b)]
    cosine = pulls[0] @ pulls[1] / max(np.linalg.norm(pulls[0]) * np.linalg.norm(pulls[1]), 1e-30)
    bands = [project_sh(np.repeat(x[..., None], 3, axis=-1), 2)[:, 0] for x in (a, b)]
    bands = [c[1:] / c[0] if c[0] > 0 else c[1:] * 0.0 for c in bands]
    return {"log_l2": float(log_l2), "level": level, "correlation": correlation,
            "direction_deg": float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))),
            "sh2_error": float(np.linalg.norm(bands[0] - bands[1]) / max(np.linalg.norm(bands[1]), 1e-30))}


def person_pixels(frame, truth) -> np.ndarray:
    """(R, R) bool: the crop pixels 2 px inside the true person's outline whose photo is not
    clipped and whose true albedo is not black (where a shading can be read off the photo)."""
    inside = compose.crop_square(truth["mask"], frame.box) > 0.5
    core = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
    albedo = compose.crop_square(truth["albedo"], frame.box)
    return core & (frame.crop.max(axis=-1) < SOLVE_CLIPPED) & (albedo @ compose.LUMINANCE > 0.02)


def stops(values: np.ndarray) -> dict:
    """log2 ratios over pixels -> their median (level) and robust spread (1.4826 x the median
    absolute deviation: shape), in stops."""
    level = float(np.median(values))
    return {"level": level, "shape": float(1.4826 * np.median(np.abs(values - level)))}


def input_errors(frame, truth, gains) -> dict:
    """The input shading the photo was divided by against the true one (`shading_a` times the
    photo's white-balance gains: the photo's units), and the albedo's level, over person_pixels:
    log2 of ours over the truth's, split into the median (level) and the spread about it
    (shape); the albedo's level error is log2 of the truth's median luminance over ours (the
    issue's sign: > 0 when ours is too dark)."""
    pixels = person_pixels(frame, truth)
    if frame.input_shading is None or not pixels.any():
        return {}
    luminance = lambda x: np.maximum(x[pixels] @ compose.LUMINANCE, 1e-9)  # noqa: E731
    ours = luminance(frame.input_shading)
    true = luminance(compose.crop_square(truth["shading_a"] * gains, frame.box))
    shading = stops(np.log2(ours / true))
    albedo = compose.crop_square(truth["albedo"], frame.box)
    level = float(np.log2(np.median(luminance(albedo)) / np.median(luminance(frame.albedo))))
    return {"shading_level": shading["level"], "shading_shape": shading["shape"], "albedo_level": level}


def albedo_metrics(frame, scene) -> dict:
    """Albedo and relit PSNR as is, with the oracle per-channel albedo gain (level and colour)
    and with the oracle level alone (one gain for the three channels)."""
    height, width = frame.image.shape[:2]
    albedo = compose.paste_back(frame.albedo, frame.box, height, width)
    relit = frame.relit
    inside = scene.mask > 0.5
    gain = scene.albedo[inside].mean(axis=0) / np.maximum(albedo[inside].mean(axis=0), 1e-6)
    level = scene.albedo[inside].mean() / max(float(albedo[inside].mean()), 1e-6)
    psnr = lambda pred, gt: layer_metrics(pred, gt, scene.mask)["psnr"]  # noqa: E731
    return {"albedo": psnr(albedo, scene.albedo), "relit": psnr(relit, scene.relit),
            "albedo_oracle_gain": psnr(albedo * gain, scene.albedo),
            "relit_oracle_gain": psnr(relit * gain, scene.relit),
            "albedo_oracle_level": psnr(albedo * level, scene.albedo),
            "relit_oracle_level": psnr(relit * level, scene.relit)}


@contextlib.contextmanager
def substituted(source: str, light: np.ndarray, level_net=None):
    """The pipeline with the truth in place of one quantity for the oracle sources: the true
    input light (in the photo's units) for the solved one, and with "-own-level" the albedo
    left at that light's level instead of the net's. LEVEL_FROM: the ratio albedo's one gain
    taken to `level_net`'s albedo (a DelightNet of another models folder, run as the stage runs
    its own) instead of the models folder's net's."""
    saved = delight.solve_input_light, compose.albedo_gain
    try:
        if source == LEVEL_FROM:
            seen = {}
            solve, gain = delight.solve_input_light, compose.albedo_gain

            def solve_and_keep(frame, net_albedo, options, models):
                seen.update(frame=frame, options=options)
                return solve(frame, net_albedo, options, models)

            def other_gain(ratio, net_albedo, mask, *args, **kwargs):
                level_albedo = delight.net_estimate(seen["frame"], level_net, seen["options"]).albedo
                return gain(ratio, level_albedo, mask, *args, **kwargs)
            delight.solve_input_light, compose.albedo_gain = solve_and_keep, other_gain
        if source.startswith("true-light"):
            def true_light(frame, net_albedo, options, models):
                delight.ensure_scenes(frame, options, models)
                frame.notes["delight"] = {"light": "the true input light (oracle)"}
                return light.astype(np.float32), light.astype(np.float32)
            delight.solve_input_light = true_light
        if source.endswith("own-level"):
            # the ratio albedo's gain to the net's level is 1: it keeps the light's own level
            # (the stage computes the gain and hands it to compose.anchor_albedo)
            compose.albedo_gain = lambda *args, **kwargs: 1.0
        yield
    finally:
        delight.solve_input_light, compose.albedo_gain = saved


def delight_once() -> None:
    """The de-lighting stage's nets (its own and --level-from's) run on the photo alone."""
    delight.MIRROR_AVERAGED = tuple(f for f in delight.MIRROR_AVERAGED if f != "delight")


def measure(folder: Path, truth: dict, source: str, use_gt_mask: bool, models, level_net=None) -> dict:
    scene = load_scene(folder)
    gains = np.asarray(json.loads((folder / "scene.json").read_text())["spec"]["augmentation"]["gains"], np.float32)
    options = RelightOptions(outputs=("relit", "albedo", "light"), method="raytrace-norefine",
                             albedo="solve" if source in ORACLES + (LEVEL_FROM,) else source, threads=2)
    image = read_image(scene.input_path)
    report = ItemReport(str(folder))
    with substituted(source, truth["light_a"] * gains, level_net):
        frame, _ = run_stages(image.rgb, scene.mask if use_gt_mask else None, load_envmap(scene.target_path),
                              options, report, models)
    return {**light_errors(frame.light, truth["light_a"] * gains), **input_errors(frame, truth, gains),
            **albedo_metrics(frame, scene), "delight_seconds": report.seconds.get("delight"),
            "note": frame.notes.get("delight")}


KEYS = ("albedo", "relit", "albedo_oracle_gain", "relit_oracle_gain", "albedo_oracle_level", "relit_oracle_level",
        "albedo_level", "shading_level", "shading_shape", "log_l2", "level", "correlation", "direction_deg",
        "sh2_error", "delight_seconds")
# Reported as root mean squares (signed errors in stops); the others as means
RMS_KEYS = ("albedo_level", "shading_level")


def summarise(rows: list) -> dict:
    done = [r for r in rows if "error" not in r]
    out = {k: float(np.mean([r[k] for r in done])) for k in KEYS}
    out.update({f"{k}_rms": float(np.sqrt(np.mean([r[k] ** 2 for r in done]))) for k in RMS_KEYS})
    out["scenes"] = len(done)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", help="eval scene folders (python -m export.factory.eval_scenes)")
    parser.add_argument("factory", help="the factory dataset they came from (its light_a)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--use-gt-mask", action="store_true")
    parser.add_argument("--sources", nargs="+", default=list(SOURCES), choices=SOURCES + ORACLES + (LEVEL_FROM,))
    parser.add_argument("--level-from", type=Path,
                        help=f"a models folder whose de-lighting net gives the albedo's level ({LEVEL_FROM})")
    parser.add_argument("--delight-once", action="store_true",
                        help="the de-lighting nets run on the photo alone, not on it and its mirror averaged")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.delight_once:
        delight_once()
    if (LEVEL_FROM in args.sources) != (args.level_from is not None):
        parser.error(f"--sources {LEVEL_FROM} and --level-from DIR go together")
    data, models = dataset.open_dataset(args.factory), Models(2)
    level_net = DelightNet(models_dir=args.level_from, threads=2) if args.level_from else None
    rows = {source: [] for source in args.sources}
    for folder in find_scenes(args.scenes):
        truth = data.load(args.split, folder.name.split("_", 1)[1])
        for source in args.sources:
            try:
                rows[source].append({"scene": folder.name, **measure(folder, truth, source, args.use_gt_mask, models, level_net)})
            except Exception as error:  # noqa: BLE001 - a failed scene is reported, the others count
                rows[source].append({"scene": folder.name, "error": str(error)})
        print(folder.name, {s: {k: round(v, 3) for k, v in rows[s][-1].items() if isinstance(v, float)}
                            for s in args.sources}, flush=True)
    summary = {source: summarise(rs) for source, rs in rows.items()}
    columns = KEYS[:7] + ("albedo_level_rms", "shading_level_rms", "shading_shape") + KEYS[9:]
    print(f"{'source':<22}" + "".join(f"{k[:18]:>19}" for k in columns))
    for source, means in summary.items():
        print(f"{source:<22}" + "".join(f"{means[k]:>19.3f}" for k in columns))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
