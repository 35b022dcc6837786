"""Build the shipped body model, `models/body_model.npz`, from the MakeHuman data (CC0 1.0).

Usage: python -m export.body_model [--samples N] [--heldout M] [--components K] [--out FILE]

What is kept
- the `body` group of the hm08 base mesh (vertices 0..13379, 26,756 triangles, closed), no
  helper geometry; the default rig (163 bones, parents before children) and its skinning
  weights restricted to the body vertices: every non-zero weight is kept (at most 9 a vertex),
  stored as (V, 9) bone ids and weights, zero-padded on the root.
- a linear shape space: PCA of N bodies drawn by the data factory (`person.sample_body`: macro
  targets, random detail targets and a sampled stature), over the stacked points
  [body vertices; bone heads; 33 landmarks], so the rest joints and landmarks follow the shape
  exactly (a joint is a mean of MakeHuman vertices, many of them helpers, hence linear in the
  full mesh). Components are scaled to unit variance (coefficient prior N(0, 1)) and signed so
  that their largest entry is positive; K is chosen by the held-out reconstruction error of M
  further factory bodies (measured errors are printed and stored in the file).
- 33 BlazePose landmarks, each one rest point posed rigidly with one bone (LANDMARKS below):
  a bone head or tail (the joint centre, as BlazePose's limb landmarks are) or one body vertex
  picked by a named MakeHuman target (the vertex that target moves most) or by a geometric rule.

Units metres; frame +Y up, the body facing +Z, its left side at +X (MakeHuman's `.L` bones).
The file is written with fixed member timestamps, so the same inputs give the same bytes.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from export.face_model import write_npz
from export.factory import assets, person
from export.factory.makehuman import read_target
from export.manifest import update_manifest

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO_ROOT / "models" / "body_model.npz"
FORMAT_VERSION = 1
SEED = 20_250_018               # issue 18: body shapes of the shape space
DEFAULT_SAMPLES = 256
DEFAULT_HELDOUT = 64
COMPONENT_CHOICES = (4, 8, 12, 16, 24, 32)
DEFAULT_COMPONENTS = 16
MAKEHUMAN_LICENSE = ("CC0 1.0 Universal: MakeHuman base mesh, targets, default rig and weights "
                     "(makehumancommunity/makehuman, makehuman/data)")

# BlazePose order. (name, rule, argument, bone that carries it). Rules:
#   head / tail      the bone's head or tail joint (mean of its MakeHuman joint vertices)
#   target_max       the vertex the target moves most (one side: argument "target|side")
#   target_mean      the mean of the vertices the target moves (the ear)
#   nose_tip         the frontmost vertex of the `nose/nose-trans-forward` region
#   heel             the rearmost vertex skinned mostly to the foot, 2 cm or more below its head
#   toe_tip          the frontmost vertex skinned mostly to toe2-1/2/3
LANDMARKS = (
    ("nose", "nose_tip", "", "head"),
    ("left_eye_inner", "target_max", "eyes/l-eye-corner2-up", "head"),
    ("left_eye", "tail", "eye.L", "eye.L"),
    ("left_eye_outer", "target_max", "eyes/l-eye-corner1-up", "head"),
    ("right_eye_inner", "target_max", "eyes/r-eye-corner2-up", "head"),
    ("right_eye", "tail", "eye.R", "eye.R"),
    ("right_eye_outer", "target_max", "eyes/r-eye-corner1-up", "head"),
    ("left_ear", "target_mean", "ears/l-ear-trans-up", "head"),
    ("right_ear", "target_mean", "ears/r-ear-trans-up", "head"),
    ("mouth_left", "target_max", "mouth/mouth-angles-up|+", "head"),
    ("mouth_right", "target_max", "mouth/mouth-angles-up|-", "head"),
    ("left_shoulder", "head", "upperarm01.L", "upperarm01.L"),
    ("right_shoulder", "head", "upperarm01.R", "upperarm01.R"),
    ("left_elbow", "head", "lowerarm01.L", "lowerarm01.L"),
    ("right_elbow", "head", "lowerarm01.R", "lowerarm01.R"),
    ("left_wrist", "head", "wrist.L", "wrist.L"),
    ("right_wrist", "head", "wrist.R", "wrist.R"),
    ("left_pinky", "head", "finger5-1.L", "finger5-1.L"),
    ("right_pinky", "head", "finger5-1.R", "finger5-1.R"),
    ("left_index", "head", "finger2-1.L", "finger2-1.L"),
    ("right_index", "head", "finger2-1.R", "finger2-1.R"),
    ("left_thumb", "head", "finger1-2.L", "finger1-2.L"),
    ("right_thumb", "head", "finger1-2.R", "finger1-2.R"),
    ("left_hip", "head", "upperleg01.L", "upperleg01.L"),
    ("right_hip", "head", "upperleg01.R", "upperleg01.R"),
    ("left_knee", "head", "lowerleg01.L", "lowerleg01.L"),
    ("right_knee", "head", "lowerleg01.R", "lowerleg01.R"),
    ("left_ankle", "head", "foot.L", "foot.L"),
    ("right_ankle", "head", "foot.R", "foot.R"),
    ("left_heel", "heel", "foot.L", "foot.L"),
    ("right_heel", "heel", "foot.R", "foot.R"),
    ("left_foot_index", "toe_tip", ".L", "toe2-3.L"),
    ("right_foot_index", "toe_tip", ".R", "toe2-3.R"),
)


def body_vertex_count(base: person.BaseModel) -> int:
    """Number of body-group vertices; raises when they are not the mesh's first ids."""
    ids = np.unique(base.mesh.faces[base.body_faces])
    if ids[0] != 0 or ids[-1] != ids.size - 1:
        raise ValueError("the body group's vertices are not 0..n-1 of base.obj")
    return int(ids.size)


def _target_ids(name: str) -> tuple[np.ndarray, np.ndarray]:
    return read_target(assets.core_path("targets") / f"{name}.target")


def _landmark_vertex(rule: str, argument: str, base: person.BaseModel, n_body: int) -> int:
    """The body vertex id of a vertex rule (see LANDMARKS), resolved on the base mesh."""
    vertices, names = base.mesh.vertices, base.skeleton.names
    dominant = np.asarray(base.weights[:n_body].argmax(axis=1)).ravel()
    if rule == "target_max":
        target, _, side = argument.partition("|")
        ids, offsets = _target_ids(target)
        moved = np.linalg.norm(offsets, axis=1)
        keep = {"+": vertices[ids, 0] > 0, "-": vertices[ids, 0] < 0, "": np.ones(len(ids), bool)}
        return int(ids[keep[side]][np.argmax(moved[keep[side]])])
    if rule == "nose_tip":
        ids, _ = _target_ids("nose/nose-trans-forward")
        return int(ids[np.argmax(vertices[ids, 2])])
    if rule == "heel":
        foot = names.index(argument)
        heads, _ = base.skeleton.joint_positions(vertices)
        ids = np.flatnonzero((dominant == foot) & (vertices[:n_body, 1] < heads[foot, 1] - 0.02))
        return int(ids[np.argmin(vertices[ids, 2])])
    if rule == "toe_tip":
        toes = [names.index(f"toe2-{k}{argument}") for k in (1, 2, 3)]
        ids = np.flatnonzero(np.isin(dominant, toes))
        return int(ids[np.argmax(vertices[ids, 2])])
    raise ValueError(f"unknown landmark rule {rule!r}")


def landmark_rows(base: person.BaseModel, n_body: int) -> list[tuple[str, str, object, int]]:
    """Per landmark (name, kind, reference, carrying bone id): kind "head"/"tail" with a bone id,
    "vertex" with a body vertex id, or "mean" with a (k,) array of body vertex ids."""
    names = base.skeleton.names
    rows = []
    for name, rule, argument, bone in LANDMARKS:
        if rule in ("head", "tail"):
            rows.append((name, rule, names.index(argument), names.index(bone)))
        elif rule == "target_mean":
            rows.append((name, "mean", _target_ids(argument)[0], names.index(bone)))
        else:
            rows.append((name, "vertex", _landmark_vertex(rule, argument, base, n_body),
                         names.index(bone)))
    return rows


def rest_points(vertices: np.ndarray, base: person.BaseModel, rows, n_body: int) -> np.ndarray:
    """(n_body + B + 33, 3) float64 m: body vertices, bone heads and landmarks of one shaped
    full mesh `vertices` (19158, 3) m in the rest pose."""
    heads, tails = base.skeleton.joint_positions(vertices)
    joint = {"head": heads, "tail": tails}
    marks = [joint[kind][ref] if kind in joint else vertices[ref].reshape(-1, 3).mean(axis=0)
             for _, kind, ref, _ in rows]
    return np.concatenate([vertices[:n_body], heads, np.stack(marks)])


def posed_landmarks(body: person.NakedBody) -> np.ndarray:
    """(33, 3) float64 m: the BlazePose landmarks of a factory person's naked body
    (person.naked_body), each rest landmark moved with its bone, as the body model poses them:
    where a perfect BlazePose would put them (bench/oracles.py's `true 3D landmarks`)."""
    base = person.base_model()
    n_body = body_vertex_count(base)
    rows = landmark_rows(base, n_body)
    marks = rest_points(body.shaped, base, rows, n_body)[-len(rows):]
    bones = body.transforms[[row[3] for row in rows]]
    return np.einsum("lij,lj->li", bones, np.c_[marks, np.ones(len(marks))])


def true_world_landmarks(body: person.NakedBody, meta: dict) -> np.ndarray:
    """(33, 3) a factory sample's naked body's BlazePose landmarks (posed_landmarks) as BlazePose
    gives its world landmarks: metres, camera-aligned axes (the sample's camera pitch and yaw
    from `meta["spec"]`), hip-centred, y down, z away from the camera."""
    from export.factory.render import camera_vertices
    from relightcli.geometry.body_model import LANDMARK_NAMES

    camera = camera_vertices(posed_landmarks(body), meta["spec"]["pitch_deg"], meta["spec"]["yaw_deg"])
    hips = [LANDMARK_NAMES.index("left_hip"), LANDMARK_NAMES.index("right_hip")]
    return (camera - camera[hips].mean(axis=0)) * np.array([1.0, -1.0, -1.0])


def sample_points(base: person.BaseModel, rows, n_body: int, first: int, count: int) -> np.ndarray:
    """(count, P, 3) float64 m: rest points of factory bodies number first..first+count-1,
    body i drawn from SeedSequence([SEED, i])."""
    out = []
    for i in range(first, first + count):
        _, shaped = person.sample_body(np.random.default_rng([SEED, i]), base)
        out.append(rest_points(shaped, base, rows, n_body))
    return np.stack(out)


def shape_space(samples: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """PCA of samples (N, P, 3): the mean (P, 3) and k components (k, P, 3) in metres per unit
    coefficient (unit variance over the samples), each signed so its largest |entry| is > 0.

    Eigenvectors of the (N, N) Gram matrix, so the work is N^2 P rather than N P^2.
    """
    mean = samples.mean(axis=0)
    centred = (samples - mean).reshape(len(samples), -1)
    gram = centred @ centred.T
    values, vectors = np.linalg.eigh(gram)
    order = np.argsort(values)[::-1][:k]
    # component c = X^T u / sqrt(lambda), scaled by the standard deviation sqrt(lambda / (N - 1))
    basis = (centred.T @ vectors[:, order]).T / np.sqrt(len(samples) - 1)
    peak = np.argmax(np.abs(basis), axis=1)
    basis *= np.sign(basis[np.arange(k), peak])[:, None]
    return mean, basis.reshape(k, *samples.shape[1:])


def reconstruction_errors(mean: np.ndarray, basis: np.ndarray, heldout: np.ndarray,
                          n_body: int) -> dict:
    """Per component count K (COMPONENT_CHOICES up to len(basis)): mean and max body-vertex
    distance (mm) between held-out bodies (M, P, 3) and their least-squares projection."""
    flat = basis[:, :n_body].reshape(len(basis), -1)
    offsets = (heldout[:, :n_body] - mean[:n_body]).reshape(len(heldout), -1)
    errors = {}
    for k in (c for c in COMPONENT_CHOICES if c <= len(basis)):
        coefficients, *_ = np.linalg.lstsq(flat[:k].T, offsets.T, rcond=None)
        residual = (offsets - coefficients.T @ flat[:k]).reshape(len(heldout), n_body, 3)
        distance = np.linalg.norm(residual, axis=2) * 1000.0
        errors[k] = {"mean_mm": round(float(distance.mean()), 3),
                     "max_mm": round(float(distance.max()), 3)}
    return errors


def skinning_table(base: person.BaseModel, n_body: int) -> tuple[np.ndarray, np.ndarray]:
    """(V, S) uint8 bone ids and (V, S) float32 weights of the body vertices, every non-zero
    weight kept (S the largest count), padding on bone 0 with weight 0; rows sum to 1."""
    weights = base.weights[:n_body].tocsr()
    weights.sort_indices()
    counts = np.diff(weights.indptr)
    slots = int(counts.max())
    bones = np.zeros((n_body, slots), np.uint8)
    values = np.zeros((n_body, slots), np.float32)
    row = np.repeat(np.arange(n_body), counts)
    column = np.arange(weights.nnz) - np.repeat(weights.indptr[:-1], counts)
    bones[row, column] = weights.indices
    values[row, column] = weights.data
    return bones, values


def build_arrays(base: person.BaseModel, samples: np.ndarray, heldout: np.ndarray,
                 components: int, rows) -> dict:
    """The arrays of the shipped model, as a name -> ndarray dict."""
    n_body = body_vertex_count(base)
    n_bones = len(base.skeleton.names)
    mean, basis = shape_space(samples, max(components, max(COMPONENT_CHOICES)))
    errors = reconstruction_errors(mean, basis, heldout, n_body)
    basis = basis[:components]
    bones, weights = skinning_table(base, n_body)
    joints = slice(n_body, n_body + n_bones)
    marks = slice(n_body + n_bones, None)
    return {
        "format_version": np.array(FORMAT_VERSION, np.int32),
        "mean_vertices": mean[:n_body].astype(np.float32),
        "triangles": base.mesh.faces[base.body_faces].astype(np.int32),
        "shape_basis": basis[:, :n_body].astype(np.float16),
        "joint_names": np.array(base.skeleton.names),
        "joint_parents": base.skeleton.parents.astype(np.int32),
        "mean_joints": mean[joints].astype(np.float32),
        "joint_basis": basis[:, joints].astype(np.float32),
        "skin_bones": bones,
        "skin_weights": weights,
        "landmark_names": np.array([row[0] for row in rows]),
        "landmark_bones": np.array([row[3] for row in rows], np.int32),
        "mean_landmarks": mean[marks].astype(np.float32),
        "landmark_basis": basis[:, marks].astype(np.float32),
        "heldout_errors_mm": np.array(json.dumps(errors, sort_keys=True)),
        "units": np.array("m"),
        "license": np.array(MAKEHUMAN_LICENSE),
        "source": np.array(f"hm08 base.obj group body, rigs/default.mhskel + default_weights.mhw;"
                           f" PCA of {len(samples)} export.factory bodies (seed {SEED})"),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=DEFAULT_SAMPLES)
    parser.add_argument("--heldout", type=int, default=DEFAULT_HELDOUT)
    parser.add_argument("--components", type=int, default=DEFAULT_COMPONENTS)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    base = person.base_model()
    n_body = body_vertex_count(base)
    rows = landmark_rows(base, n_body)
    samples = sample_points(base, rows, n_body, 0, args.samples)
    heldout = sample_points(base, rows, n_body, args.samples, args.heldout)
    arrays = build_arrays(base, samples, heldout, args.components, rows)
    digest = write_npz(args.out, arrays)
    update_manifest(args.out.parent, "body_model", {
        "kind": "data", "file": args.out.name, "sha256": digest, "license": MAKEHUMAN_LICENSE,
        "description": (f"MakeHuman hm08 body group ({n_body} vertices, metres, +Y up, facing +Z)"
                        f", default rig ({len(base.skeleton.names)} bones, LBS weights), "
                        f"{args.components}-component PCA shape space of factory bodies, "
                        "33 BlazePose landmarks. Built by python -m export.body_model.")})
    print(json.dumps({"file": args.out.name, "sha256": digest, "bytes": args.out.stat().st_size,
                      "components": args.components,
                      "heldout_errors_mm": json.loads(str(arrays["heldout_errors_mm"]))}))


if __name__ == "__main__":
    main()
