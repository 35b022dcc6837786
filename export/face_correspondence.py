"""The table from MediaPipe's 468-point face mesh to the 68 iBUG landmarks of the ICT face
model, measured on renders of that model: `python -m export.face_correspondence [--models models]`.

Near-frontal ICT faces (export/factory/faces.py: random identity, expression, look, lighting;
yaw within +-20, pitch and roll within +-10 degrees, framed as the runtime's face crop, 128 px)
are rendered with their true iBUG landmarks (the model's landmark vertices projected); the
runtime's face chain (relightcli.nets.face_mesh.find_face on the whole crop) gives the 468
mesh points. For each iBUG landmark the table keeps the mesh point, or the midpoint of two of
the `CANDIDATES` nearest, with the smallest median distance over the FIT_SAMPLES renders. The
jaw-line landmarks (0-16) are fixed vertices of the model's jaw, as the mesh's outline points
are fixed points of its face: both lie on the silhouette only near frontal, so the table is
measured near frontal and the fit (which projects the same vertices) stays consistent.
The distances reported (and written to the manifest) are on HELD_OUT_SAMPLES other renders.

Output: models/face_correspondence.npz with `mesh_points` (68, 2) int16 and `weights` (68, 2)
float32 (rows sum to 1): iBUG landmark i = sum_k weights[i, k] * mesh[mesh_points[i, k]]; and
its manifest entry ("kind": "data").
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import replace
from pathlib import Path

import numpy as np

from export.face_model import write_npz
from export.factory import faces, lighting
from export.manifest import update_manifest
from relightcli.geometry.face_model import FaceModel

FIT_SAMPLES, HELD_OUT_SAMPLES = 48, 24
FIT_SEED, HELD_OUT_SEED = 0, 1
POSE_LIMITS_DEG = (20.0, 10.0, 10.0)   # |yaw|, |pitch|, |roll| of the renders
CANDIDATES = 6                          # nearest single points whose midpoints are tried too
FILE = "face_correspondence.npz"
LICENSE = ("MIT License, Copyright (c) 2020 USC Institute for Creative Technologies (ICT FaceKit "
           "landmarks); Apache-2.0 (MediaPipe face mesh topology, models/LICENSE.mediapipe)")


def near_frontal_spec(rng: np.random.Generator, model: FaceModel, hdris) -> faces.FaceSpec:
    """A face sample as the landmark data has them, turned less, framed as the runtime's
    canonical face crop, without the low-resolution and JPEG degradations."""
    spec = faces.sample_spec(rng, model, hdris)
    angles = tuple(float(rng.uniform(-a, a)) for a in POSE_LIMITS_DEG)
    return replace(spec, angles_deg=angles, crop_scale=faces.CANONICAL_FRAMING["scale"],
                   crop_shift=faces.CANONICAL_FRAMING["shift"], source_side=0, jpeg_quality=0)


def mesh_and_truth(seed: int, count: int, model: FaceModel, detector, mesh) -> tuple[np.ndarray, np.ndarray]:
    """(mesh (N, 468, 2), truth (N, 68, 2)) pixel indices (col, row) of the 128 crop, for the
    renders where the face chain finds the face (N <= count)."""
    from relightcli.nets.face_mesh import find_face

    hdris = lighting.hdri_splits()["train"]
    rng = np.random.default_rng(seed)
    found, truth = [], []
    for _ in range(count):
        out = faces.render_face(model, near_frontal_spec(rng, model, hdris))
        face, _ = find_face(out["image"].astype(np.float32) / 255.0, None, detector, mesh)
        if face is not None:
            found.append(face.mesh.points[:, :2] - 0.5)  # continuous -> pixel index
            truth.append(out["landmarks"].astype(np.float64))
    return np.asarray(found), np.asarray(truth)


def combine(mesh: np.ndarray, points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(..., 68, 2) landmarks from mesh points (..., 468, 2) through a table."""
    return np.einsum("...ikc,ik->...ic", mesh[..., points, :], weights)


def choose_table(mesh: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mesh_points (68, 2) int, weights (68, 2)) minimising each landmark's median distance:
    the best single point, or the midpoint of two of its CANDIDATES nearest singles."""
    # (468, 68) median distance of each mesh point to each landmark over the renders
    single = np.median(np.linalg.norm(mesh[:, :, None, :] - truth[:, None, :, :], axis=-1), axis=0)
    points = np.zeros((truth.shape[1], 2), np.int64)
    weights = np.zeros((truth.shape[1], 2), np.float64)
    for i in range(truth.shape[1]):
        nearest = np.argsort(single[:, i])[:CANDIDATES]
        best, best_cost = (nearest[0], nearest[0]), single[nearest[0], i]
        for a, b in itertools.combinations(nearest, 2):
            midpoint = (mesh[:, a] + mesh[:, b]) / 2.0
            cost = np.median(np.linalg.norm(midpoint - truth[:, i], axis=-1))
            if cost < best_cost:
                best, best_cost = (a, b), cost
        points[i] = best
        weights[i] = (1.0, 0.0) if best[0] == best[1] else (0.5, 0.5)
    return points, weights


def distances(mesh: np.ndarray, truth: np.ndarray, points, weights) -> dict:
    """Median, p90 and max distance (pixels of the 128 crop) of the table's landmarks to the truth."""
    error = np.linalg.norm(combine(mesh, points, weights) - truth, axis=-1)
    return {"median_px": round(float(np.median(error)), 3), "p90_px": round(float(np.percentile(error, 90)), 3),
            "max_px": round(float(error.max()), 3), "renders": int(error.shape[0])}


def main(argv: list[str] | None = None) -> int:
    from relightcli.nets.face_mesh import FaceDetector, FaceMesh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="models", help="folder of manifest.json (default models)")
    args = parser.parse_args(argv)
    model = FaceModel.load()
    detector, mesh = FaceDetector(threads=1), FaceMesh(threads=1)
    fit_mesh, fit_truth = mesh_and_truth(FIT_SEED, FIT_SAMPLES, model, detector, mesh)
    points, weights = choose_table(fit_mesh, fit_truth)
    held_mesh, held_truth = mesh_and_truth(HELD_OUT_SEED, HELD_OUT_SAMPLES, model, detector, mesh)
    metrics = {"fit": distances(fit_mesh, fit_truth, points, weights),
               "held_out": distances(held_mesh, held_truth, points, weights),
               "found": {"fit": f"{len(fit_mesh)}/{FIT_SAMPLES}", "held_out": f"{len(held_mesh)}/{HELD_OUT_SAMPLES}"}}
    sha = write_npz(Path(args.models) / FILE, {"mesh_points": points.astype(np.int16),
                                               "weights": weights.astype(np.float32)})
    update_manifest(args.models, "face_correspondence", {
        "kind": "data", "file": FILE, "sha256": sha, "license": LICENSE,
        "description": "MediaPipe face mesh (468 points) -> the ICT face model's 68 iBUG landmarks: "
                       "per landmark two mesh points and their weights. Built by python -m "
                       "export.face_correspondence from renders of models/face_model.npz "
                       f"(distances in pixels of the 128 face crop: {metrics})"})
    print(metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
