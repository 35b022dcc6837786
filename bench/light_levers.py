"""Levers on the input light, measured offline on the light solve's own inputs (issue 47).

    python bench/light_levers.py capture data/evalval512 data/factory512val --split val --cache data/lightcache/val
    python bench/light_levers.py levers data/lightcache/val [--only today parametric]
    python bench/light_levers.py level data/lightcache/train data/lightcache/val data/lightcache/test

`capture` runs the default pipeline (`raytrace-norefine`, the true mask) on every scene folder
and keeps, per scene, what `stages.delight.solve_input_light` solves from (the light transport
of its pixels, the photo and the net's albedo there, the net's light, the solved light) with
the factory's truth cropped alike (albedo, input shading `shading_a` times the photo's
white-balance gains, the input light `light_a` times them). `levers` solves the light again
under each variant and scores it at the solve's pixels (inside the true mask, not clipped,
true albedo > 0.02): the albedo = photo / (transport x light) against the truth, as PSNR at
its own level and with an oracle level (the truth's median luminance), the level's error in
stops (RMS over scenes), the input shading's shape (robust spread of log2 ours / true, level
apart) and the light's dominant direction against the truth's. A variant that does not beat
"today" at the oracle level does not fix the light's shape. `level` fits log2 of the true
albedo's median luminance on the net albedo's statistics on the first folder and scores the
fit's RMS error on the others (is the level predictable from what the net gives?).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from light_solve import light_errors  # noqa: E402

from relightcli import compose  # noqa: E402
from relightcli.render.inverse import Transport, albedo_regions, solve_light, solve_light_by_regions  # noqa: E402
from relightcli.stages import delight  # noqa: E402

LUMINANCE = compose.LUMINANCE


def capture(scenes: str, factory: str, split: str, cache: Path) -> None:
    import json

    from scene_run import replaced, run_scene

    from export.factory import dataset
    from relightcli.evaluate import find_scenes
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.frame import Models

    cache.mkdir(parents=True, exist_ok=True)
    data, models, kept = dataset.open_dataset(factory), Models(2), {}
    solve = delight.solve_input_light

    def keeping(frame, net_albedo, options, models):
        delight.ensure_scenes(frame, options, models)
        pixels = delight.solve_pixels(frame)
        kept.update(matrix=delight.mesh_transport(frame, pixels, options.seed).matrix, pixels=pixels,
                    photo=frame.crop.reshape(-1, 3)[pixels], net_albedo=net_albedo.reshape(-1, 3)[pixels],
                    mask=frame.crop_mask.reshape(-1)[pixels], net_light=frame.light)
        solved, layer = solve(frame, net_albedo, options, models)
        kept["solved_light"] = solved
        return solved, layer

    options = RelightOptions(outputs=("relit",), method="raytrace-norefine", threads=2)
    with replaced(delight, "solve_input_light", keeping):
        for folder in find_scenes(scenes):
            truth = data.load(split, folder.name.split("_", 1)[1])
            gains = np.asarray(json.loads((folder / "scene.json").read_text())["spec"]["augmentation"]["gains"])
            kept.clear()
            frame = run_scene(folder, options, models)
            at = lambda image, box=frame.box: compose.crop_square(np.asarray(image, np.float32), box).reshape(  # noqa: E731
                -1, *np.shape(image)[2:])[kept["pixels"]]
            np.savez_compressed(cache / f"{folder.name}.npz", **kept, true_albedo=at(truth["albedo"]),
                                true_shading=at(truth["shading_a"]) * gains, true_mask=at(truth["mask"]),
                                true_light=truth["light_a"] * gains)
            print(folder.name, flush=True)


def load(path: Path) -> dict:
    z = {key: value.astype(np.float64) if value.dtype.kind == "f" else value for key, value in np.load(path).items()}
    z["usable"] = (z["photo"].max(axis=1) < delight.SOLVE_CLIPPED) & (z["net_albedo"].mean(axis=1) >= delight.SOLVE_DARK_ALBEDO)
    z["scored"] = z["usable"] & (z["true_mask"] > 0.99) & (z["true_albedo"] @ LUMINANCE > 0.02)
    return z


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean(np.square(a - b)) + 1e-12))


def score(light: np.ndarray, z: dict) -> dict:
    """The albedo and input shading a light gives at the scored pixels, and its direction."""
    pixels = z["scored"]
    shading = (z["matrix"] @ light.reshape(-1, 3))[pixels]
    albedo = np.maximum(z["photo"][pixels] / np.maximum(shading, 1e-6), 0.0)
    truth = z["true_albedo"][pixels]
    level = float(np.log2(np.median(truth @ LUMINANCE) / max(np.median(albedo @ LUMINANCE), 1e-9)))
    ratio = np.log2(np.maximum(shading @ LUMINANCE, 1e-9) / np.maximum(z["true_shading"][pixels] @ LUMINANCE, 1e-9))
    return {"albedo": psnr(np.clip(albedo, 0.0, 1.0), truth),
            "albedo_oracle_level": psnr(np.clip(albedo * 2.0 ** level, 0.0, 1.0), truth),
            "level": level, "shading_shape": float(1.4826 * np.median(np.abs(ratio - np.median(ratio)))),
            "direction_deg": light_errors(light, z["true_light"])["direction_deg"]}


def solved(z: dict, albedo: np.ndarray | None = None, weights: np.ndarray | None = None, **settings) -> np.ndarray:
    transport = Transport(z["matrix"].astype(np.float32), z["pixels"], (16, 32))
    weights = z["usable"].astype(np.float64) if weights is None else weights
    albedo = z["net_albedo"] if albedo is None else albedo
    return delight.grey_light(solve_light(transport, z["photo"], albedo, weights, z["net_light"], **settings).light)


def sharpened(z: dict, beta: float) -> np.ndarray:
    """The net's albedo with a share beta of the shading taken back out: if the net left
    shading^beta in its albedo, photo / albedo = shading^(1 - beta) (at the net's level)."""
    usable = z["usable"]
    ratio = (z["photo"] @ LUMINANCE) / np.maximum(z["net_albedo"] @ LUMINANCE, 1e-4)
    shading = np.maximum(ratio / np.median(ratio[usable]), 1e-3) ** (1.0 / (1.0 - beta))
    albedo = z["photo"] / shading[:, None]
    return albedo * (np.median(z["net_albedo"][usable] @ LUMINANCE) / np.median(albedo[usable] @ LUMINANCE))


def region_gains(z: dict, k: int, rounds: int = 4) -> np.ndarray:
    """Light and a gain per region of the net's albedo solved in turn (regions: k-means over
    the photo's chromaticity and the net albedo's log luminance), the gains' log mean held at
    0: the net's albedo level kept, its regions' relative levels freed."""
    usable = z["usable"]
    labels, gains = albedo_regions(z["photo"], z["net_albedo"], k), np.ones(k)
    for _ in range(rounds):
        light = solved(z, z["net_albedo"] * gains[labels][:, None])
        fit = (z["net_albedo"] @ LUMINANCE) * ((z["matrix"] @ light.reshape(-1, 3)) @ LUMINANCE)
        for j in range(k):
            pick = usable & (labels == j)
            if pick.sum() >= 20:
                gains[j] = max(float((fit[pick] * (z["photo"][pick] @ LUMINANCE)).sum() / max(np.square(fit[pick]).sum(), 1e-12)), 1e-3)
        counts = np.bincount(labels[usable], minlength=k)
        gains /= np.exp((counts * np.log(gains)).sum() / max(counts.sum(), 1))
    return solved(z, z["net_albedo"] * gains[labels][:, None])


def by_regions(z: dict, regions: int, **settings) -> np.ndarray:
    """The product's solve_light_by_regions: one albedo colour per region, solved with the light."""
    transport = Transport(z["matrix"].astype(np.float32), z["pixels"], (16, 32))
    return delight.grey_light(solve_light_by_regions(transport, z["photo"], z["net_albedo"], z["usable"].astype(np.float64),
                                                     z["net_light"], regions, **settings).light)


def reweighted(z: dict, sigma: float, rounds: int = 3) -> np.ndarray:
    """Iteratively reweighted: pixels whose photo the fit misses by much (the net's albedo
    wrong there) count less (Cauchy weights on the log residual, sigma in nats)."""
    weights = z["usable"].astype(np.float64)
    for _ in range(rounds):
        fit = ((z["matrix"] @ solved(z, weights=weights).reshape(-1, 3)) * z["net_albedo"]) @ LUMINANCE
        residual = np.log(np.maximum(z["photo"] @ LUMINANCE, 1e-4) / np.maximum(fit, 1e-4))
        residual -= np.median(residual[z["usable"]])
        weights = z["usable"] / (1.0 + np.square(residual / sigma))
    return solved(z, weights=weights)


def sky_lobes(height: int = 16, width: int = 32, count: int = 14, sharpness: float = 2.0) -> np.ndarray:
    """(H*W, count + 1) non-negative smooth lights: a constant and `count` wide lobes
    exp(sharpness (d.a - 1)) about the cube's 6 face and 8 corner directions."""
    from relightcli.io.envmap import texel_directions

    axes = np.concatenate([np.eye(3), -np.eye(3), np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1)
                                                            for z in (-1, 1)]) / np.sqrt(3)])[:count]
    d = texel_directions(height, width).reshape(-1, 3)
    return np.concatenate([np.ones((d.shape[0], 1)), np.exp(sharpness * (d @ axes.T - 1.0))], axis=1)


def sun_and_sky(z: dict, seen_share: float = 0.02, with_sun: bool = True, relative: bool = True) -> np.ndarray:
    """A parametric light fitted to the photo's luminance over the net's: a non-negative sky of
    wide lobes (sky_lobes) plus one sun in a single texel, every texel the pixels see tried as
    the sun's (non-negative least squares on the relative residual each), the best kept; grey."""
    from scipy.optimize import nnls

    usable = z["usable"]
    photo, albedo = z["photo"][usable] @ LUMINANCE, z["net_albedo"][usable] @ LUMINANCE
    matrix = z["matrix"][usable]
    w = 1.0 / np.maximum(photo, 1e-3) if relative else np.ones_like(photo)
    lobes = sky_lobes()
    sky = (albedo * w)[:, None] * (matrix @ lobes)
    target = photo * w
    seen = np.maximum(matrix, 0.0).sum(axis=0)
    best = (np.inf, None, None)
    for texel in (np.flatnonzero(seen >= seen_share * seen.max()) if with_sun else [None]):
        design = sky if texel is None else np.concatenate([sky, (albedo * w * matrix[:, texel])[:, None]], axis=1)
        x, residual = nnls(design, target, maxiter=50 * design.shape[1])
        if residual < best[0]:
            best = (residual, texel, x)
    _, texel, x = best
    light = lobes @ x[:lobes.shape[1]]
    if texel is not None:
        light[texel] += x[-1]
    return np.repeat(light.reshape(16, 32, 1), 3, axis=-1)


LEVERS = {
    "today (the solved light)": lambda z: z["solved_light"],
    "the de-lighting net's light": lambda z: z["net_light"],
    "the true light": lambda z: z["true_light"],
    "solve with the true albedo": lambda z: solved(z, z["true_albedo"]),
    "  its colour kept (not made grey)": lambda z: solve_light(
        Transport(z["matrix"].astype(np.float32), z["pixels"], (16, 32)), z["photo"], z["true_albedo"],
        z["usable"].astype(np.float64), z["net_light"]).light,
    "shading taken out of the net's albedo, beta 0.2": lambda z: solved(z, sharpened(z, 0.2)),
    "  beta 0.35": lambda z: solved(z, sharpened(z, 0.35)),
    "  beta 0.5": lambda z: solved(z, sharpened(z, 0.5)),
    "a gain per region, 3 regions": lambda z: region_gains(z, 3),
    "  6 regions": lambda z: region_gains(z, 6),
    "  10 regions": lambda z: region_gains(z, 10),
    "reweighted, sigma 0.2": lambda z: reweighted(z, 0.2),
    "  sigma 0.8": lambda z: reweighted(z, 0.8),
    "smoothness 1 (10)": lambda z: solved(z, smoothness=1.0),
    "smoothness 100": lambda z: solved(z, smoothness=100.0),
    "prior weight 0.01 (0.1)": lambda z: solved(z, prior_weight=0.01),
    "prior weight 1": lambda z: solved(z, prior_weight=1.0),
    "quadratic smoothing": lambda z: solved(z, edge_scale=None),
    "4 rounds (2)": lambda z: solved(z, rounds=4),
    "one albedo colour per region, 3 regions": lambda z: by_regions(z, 3),
    "  one colour, 6 regions": lambda z: by_regions(z, 6),
    "  one colour, 12 regions": lambda z: by_regions(z, 12),
    "  one colour, 6 regions, 2 rounds (4)": lambda z: by_regions(z, 6, rounds=2),
    "  one colour, 6 regions, 1 round": lambda z: by_regions(z, 6, rounds=1),
    "  one colour, 6 regions, 0 rounds (the net's mean per region)": lambda z: by_regions(z, 6, rounds=0),
    "  one colour, 3 regions, 0 rounds": lambda z: by_regions(z, 3, rounds=0),
    "  one colour, 10 regions, 0 rounds": lambda z: by_regions(z, 10, rounds=0),
    "parametric: sky lobes alone": lambda z: sun_and_sky(z, with_sun=False),
    "parametric: sky lobes + one sun texel": sun_and_sky,
    "  absolute residuals, sky alone": lambda z: sun_and_sky(z, with_sun=False, relative=False),
    "  absolute residuals, + sun": lambda z: sun_and_sky(z, relative=False),
}


def levers(cache: Path, only: list | None = None) -> None:
    scenes = [load(path) for path in sorted(cache.glob("*.npz"))]
    print(f"{len(scenes)} scenes; albedo dB (own level / oracle level), level error RMS (stops), "
          "input shading shape (stops), light direction error (deg)")
    for name, lever in LEVERS.items():
        if only and not any(part in name for part in only):
            continue
        rows = [score(lever(z), z) for z in scenes]
        mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
        rms = float(np.sqrt(np.mean([r["level"] ** 2 for r in rows])))
        print(f"{name:<50} {mean('albedo'):6.2f} / {mean('albedo_oracle_level'):6.2f}  {rms:5.2f}  "
              f"{mean('shading_shape'):5.3f}  {mean('direction_deg'):5.1f}", flush=True)


def level_features(cache: Path) -> np.ndarray:
    """Per scene: log2 of the true albedo's median luminance, then the net albedo's median and
    mean and the photo's median, over the solve's usable pixels inside the mask."""
    rows = []
    for path in sorted(cache.glob("*.npz")):
        z = load(path)
        usable = z["usable"] & (z["mask"] > 0.5)
        net = z["net_albedo"][usable] @ LUMINANCE
        rows.append([np.log2(np.median(z["true_albedo"][z["scored"]] @ LUMINANCE)), np.log2(np.median(net)),
                     np.log2(np.mean(net)), np.log2(np.median(z["photo"][usable] @ LUMINANCE))])
    return np.array(rows)


def level(caches: list) -> None:
    sets = [(cache.name, level_features(cache)) for cache in caches]
    for name, x in sets:
        error = x[:, 1] - x[:, 0]
        print(f"{name}: {len(x)} scenes, true level {x[:, 0].mean():+.2f} +- {x[:, 0].std():.2f} stops; the net's "
              f"error {error.mean():+.2f} mean, {np.sqrt(np.mean(error ** 2)):.2f} RMS; correlation "
              f"{np.corrcoef(x[:, 1], x[:, 0])[0, 1]:.2f}")
    fitted = sets[0][1]
    for label, columns in (("a constant", []), ("the net's median", [1]), ("its mean", [2]),
                           ("its median and the photo's", [1, 3])):
        design = lambda x: np.column_stack([x[:, columns], np.ones(len(x))])  # noqa: E731
        coefficients = np.linalg.lstsq(design(fitted), fitted[:, 0], rcond=None)[0]
        errors = [np.sqrt(np.mean(np.square(design(x) @ coefficients - x[:, 0]))) for _, x in sets]
        print(f"fitted on {sets[0][0]}, {label:<28} " + "  ".join(f"{n} {e:.2f}" for (n, _), e in zip(sets, errors)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    keep = commands.add_parser("capture")
    keep.add_argument("scenes")
    keep.add_argument("factory")
    keep.add_argument("--split", default="val")
    keep.add_argument("--cache", type=Path, required=True)
    chosen = commands.add_parser("levers")
    chosen.add_argument("cache", type=Path)
    chosen.add_argument("--only", nargs="+", help="the levers whose names contain one of these")
    commands.add_parser("level").add_argument("caches", type=Path, nargs="+")
    args = parser.parse_args()
    if args.command == "capture":
        capture(args.scenes, args.factory, args.split, args.cache)
    elif args.command == "levers":
        levers(args.cache, args.only)
    else:
        level(args.caches)
    return 0


if __name__ == "__main__":
    sys.exit(main())
