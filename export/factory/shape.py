"""Random body shapes from MakeHuman's macro targets plus a sample of detail targets.

Macro weighting (worked out from the target file names; an approximation of MakeHuman's own
modifiers, documented in export/README.md). Each macro variable lives in [0, 1] and is split
into weights on the corners named in the file names by piecewise-linear interpolation:

- gender g:        female = 1 - g, male = g
- age a:           knots baby 0, child 0.1875, young 0.5, old 1 (MakeHuman: 1, 11, 25, 90 years)
- muscle, weight:  knots min 0, average 0.5, max 1
- height h:        minheight = max(0, 1 - 2h), maxheight = max(0, 2h - 1)   (0.5 is neutral)
- proportions p:   uncommon = max(0, 1 - 2p), ideal = max(0, 2p - 1)        (0.5 is neutral)
- race:            african, asian, caucasian weights summing to 1

Files and their weight (products of the corner weights, so each family sums to its variable):
  `{race}-{gender}-{age}`                                      race * gender * age
  `universal-{gender}-{age}-{muscle}muscle-{weight}weight`     gender * age * muscle * weight
  `height/{...}-{min|max}height`                               ... * height corner
  `proportions/{...}-{uncommon|ideal}proportions`              ... * proportions corner
Detail targets (torso, hips, nose, limbs, ...) are added with small random weights.
Breast and genital macros are left at MakeHuman's neutral (not applied).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from relightcli.errors import InputError

from . import assets
from .makehuman import read_target

RACES = ("african", "asian", "caucasian")
AGE_KNOTS = {"baby": 0.0, "child": 0.1875, "young": 0.5, "old": 1.0}
THREE_KNOTS = {"min": 0.0, "average": 0.5, "max": 1.0}
DETAIL_FOLDERS = ("torso", "hip", "stomach", "buttocks", "neck", "head", "nose", "chin",
                  "cheek", "mouth", "ears", "forehead", "eyebrows", "armslegs", "measure")
DETAIL_MAX_WEIGHT = 0.5


@dataclass(frozen=True)
class ShapeParams:
    """Body-shape parameters; every macro in [0, 1] on MakeHuman's scale.

    gender: 0 female .. 1 male. age: 0.5 = 25 years .. 1 = 90 years (0 baby, 0.1875 child).
    muscle, weight, height, proportions: 0.5 neutral. race: (african, asian, caucasian), sum 1.
    details: (target path relative to `targets/`, weight) pairs.
    """

    gender: float
    age: float
    muscle: float
    weight: float
    height: float
    proportions: float
    race: tuple[float, float, float]
    details: tuple[tuple[str, float], ...] = field(default=())

    def as_dict(self) -> dict:
        return asdict(self)


def knot_weights(value: float, knots: dict[str, float]) -> dict[str, float]:
    """Piecewise-linear (hat function) weights of `value` on named knots; they sum to 1."""
    names = list(knots)
    x = float(np.clip(value, knots[names[0]], knots[names[-1]]))
    weights = {}
    for k, name in enumerate(names):
        xs = [knots[n] for n in names]
        hat = np.zeros(len(names))
        hat[k] = 1.0
        weights[name] = float(np.interp(x, xs, hat))
    return {n: w for n, w in weights.items() if w > 0.0}


def _side_weights(value: float, low: str, high: str) -> dict[str, float]:
    weights = {low: max(0.0, 1.0 - 2.0 * value), high: max(0.0, 2.0 * value - 1.0)}
    return {n: w for n, w in weights.items() if w > 0.0}


def macro_target_weights(params: ShapeParams) -> dict[str, float]:
    """Target file (relative to `targets/`) -> weight for the macro variables of `params`."""
    genders = {n: w for n, w in (("female", 1.0 - params.gender), ("male", params.gender)) if w > 0}
    ages = knot_weights(params.age, AGE_KNOTS)
    muscles = knot_weights(params.muscle, THREE_KNOTS)
    weights_ = knot_weights(params.weight, THREE_KNOTS)
    heights = _side_weights(params.height, "minheight", "maxheight")
    props = _side_weights(params.proportions, "uncommonproportions", "idealproportions")
    out: dict[str, float] = {}
    for g, wg in genders.items():
        for a, wa in ages.items():
            for race, wr in zip(RACES, params.race):
                if wr > 0:
                    out[f"macrodetails/{race}-{g}-{a}.target"] = wr * wg * wa
            for m, wm in muscles.items():
                for w, ww in weights_.items():
                    stem = f"{g}-{a}-{m}muscle-{w}weight"
                    base = wg * wa * wm * ww
                    out[f"macrodetails/universal-{stem}.target"] = base
                    for h, wh in heights.items():
                        out[f"macrodetails/height/{stem}-{h}.target"] = base * wh
                    for p, wp in props.items():
                        out[f"macrodetails/proportions/{stem}-{p}.target"] = base * wp
    return out


def detail_target_names() -> list[str]:
    """All detail targets we sample from, relative to `targets/`, sorted."""
    root = assets.core_path("targets")
    return sorted(str(p.relative_to(root)) for folder in DETAIL_FOLDERS
                  for p in (root / folder).rglob("*.target"))


def sample_shape(rng: np.random.Generator, n_details: tuple[int, int] = (4, 12)) -> ShapeParams:
    """Random adult shape: uniform macros in plausible ranges plus a few detail targets."""
    names = detail_target_names()
    count = int(rng.integers(n_details[0], n_details[1] + 1))
    picked = rng.choice(len(names), size=count, replace=False)
    return ShapeParams(
        gender=float(rng.uniform(0.0, 1.0)),
        age=float(rng.uniform(0.5, 0.9)),            # 25 to ~77 years
        muscle=float(rng.uniform(0.2, 0.85)),
        weight=float(rng.uniform(0.15, 0.9)),
        height=float(rng.uniform(0.1, 0.9)),
        proportions=float(rng.uniform(0.3, 1.0)),
        race=tuple(float(x) for x in rng.dirichlet([0.6, 0.6, 0.6])),
        details=tuple((names[k], float(rng.uniform(0.0, DETAIL_MAX_WEIGHT)))
                      for k in sorted(picked)),
    )


def all_target_weights(params: ShapeParams) -> dict[str, float]:
    """Macro and detail targets together: relative path -> weight."""
    weights = macro_target_weights(params)
    for name, w in params.details:
        weights[name] = weights.get(name, 0.0) + w
    return weights


def apply_targets(vertices: np.ndarray, weights: dict[str, float]) -> np.ndarray:
    """Base vertices (V, 3) m plus the weighted sum of target offsets; returns a new array."""
    shaped = vertices.copy()
    for name, w in weights.items():
        path = assets.core_path("targets") / name
        if not path.is_file():
            raise InputError("MakeHuman target file missing", path=path,
                             fix="re-extract the cache (delete export/.cache/makehuman)")
        ids, offsets = read_target(path)
        if ids.size and ids.max() >= len(vertices):
            raise InputError("target refers to a vertex beyond the base mesh", path=path)
        np.add.at(shaped, ids, w * offsets)
    return shaped


def max_displacement_bound(weights: dict[str, float]) -> np.ndarray:
    """Per-vertex upper bound (V,) m on |shaped - base|: sum_t |w_t| |d_t(v)| (triangle
    inequality); V is the highest vertex id any target touches, plus one."""
    bound = None
    for name, w in weights.items():
        ids, offsets = read_target(assets.core_path("targets") / name)
        if bound is None:
            bound = np.zeros(0)
        size = max(bound.size, int(ids.max()) + 1 if ids.size else 0)
        bound = np.pad(bound, (0, size - bound.size))
        np.add.at(bound, ids, abs(w) * np.linalg.norm(offsets, axis=1))
    return bound if bound is not None else np.zeros(0)


def stature(vertices: np.ndarray, body_ids: np.ndarray) -> float:
    """Standing height (m): vertical extent of the body vertices in the rest pose."""
    ys = vertices[body_ids, 1]
    return float(ys.max() - ys.min())


def sample_stature(rng: np.random.Generator, gender: float) -> float:
    """Target standing height (m): normal around 1.63 m (female) .. 1.76 m (male), sd 7 cm,
    clipped to [1.45, 2.00] m (adult population ranges)."""
    return float(np.clip(rng.normal(1.63 + 0.13 * gender, 0.07), 1.45, 2.0))


def solve_height_param(params: ShapeParams, base_vertices: np.ndarray, body_ids: np.ndarray,
                       stature_m: float) -> float:
    """The `height` macro in [0, 1] giving standing height `stature_m` for the other params.

    The height targets are linear, so stature is evaluated at h = 0, 0.5, 1 and inverted
    piecewise linearly (clamped to the reachable range).
    """
    knots = np.array([0.0, 0.5, 1.0])
    heights = []
    for h in knots:
        trial = ShapeParams(**{**params.as_dict(), "height": float(h), "race": params.race,
                               "details": params.details})
        heights.append(stature(apply_targets(base_vertices, all_target_weights(trial)), body_ids))
    heights = np.maximum.accumulate(np.asarray(heights))  # guard against a non-monotone corner
    return float(np.interp(stature_m, heights, knots))
