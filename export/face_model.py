"""Build the shipped face model, `models/face_model.npz`, from the ICT FaceKit light model.

Usage: python -m export.face_model [--ict DIR] [--out FILE] [--identity-modes K]

Source: `../shared/data/ict_facekit/ict_facemodel_light.npz` (26,719 vertices, 100 identity and
57 expression modes; MIT, Copyright (c) 2020 USC Institute for Creative Technologies).

What is kept (see the ICT FaceKit README for the vertex ranges):
- vertices 0..11247: the face (0..9408) and the head and neck (9409..11247); eyeballs, teeth,
  gums, sockets and eyelashes are dropped, as are faces touching them. Quads are split into two
  triangles (0, 1, 2), (0, 2, 3), which keeps ICT's outward winding.
- the eye and mouth openings are closed with a triangle fan around one extra vertex per hole,
  the mean of the hole's boundary vertices (its deltas are the same mean, so the model stays
  linear); the neck opening is left open. The face region is vertices 0..9408 plus the
  three hole centres.
- the first K identity modes (default 40) and every expression mode that moves a kept vertex
  by 0.01 cm or more (PupilDilate_L/R do not and are dropped: 55 of 57 stay), deltas stored
  as float16 (their error, < 1e-3 cm, is far below what a single image resolves).
- 68 landmarks: ICT's own `idx_to_landmark_verts` (vertex_indices.json), which follow the
  iBUG-300W 68-point order: 0-16 jaw line from the image-left ear to the image-right ear (the
  subject's right side first), 17-21 / 22-26 brows, 27-30 nose bridge to tip, 31-35 nostrils,
  36-41 / 42-47 eyes (outer corner first, clockwise in the image), 48-59 outer lip contour
  (48 and 54 the mouth corners), 60-67 inner lip contour. The script checks this order by
  geometry on the neutral mesh (mirror pairs, ordering along x and y) before writing.

Units: centimetres, model frame +X to the subject's left (image right in a frontal view), +Y up,
+Z out of the face. The file is a plain zip of .npy members written with fixed timestamps, so the
same inputs always give the same bytes (and sha256).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from relightcli.errors import MissingDependencyError

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ICT_DIR = REPO_ROOT / ".." / "shared" / "data" / "ict_facekit"
DEFAULT_OUT = REPO_ROOT / "models" / "face_model.npz"
FORMAT_VERSION = 1
FACE_VERTICES = 9409          # ICT range 0..9408: the face
HEAD_NECK_VERTICES = 11248    # ICT range 9409..11247: head and neck
DEFAULT_IDENTITY_MODES = 40
MIN_EXPRESSION_MOTION = 0.01  # cm: modes moving no kept vertex farther are dropped
ICT_LICENSE = "MIT License, Copyright (c) 2020 USC Institute for Creative Technologies"
LANDMARK_NAMES = (
    [f"jaw_{k:02d}" for k in range(17)]
    + [f"brow_right_{k}" for k in range(5)] + [f"brow_left_{k}" for k in range(5)]
    + [f"nose_bridge_{k}" for k in range(4)] + [f"nostril_{k}" for k in range(5)]
    + [f"eye_right_{k}" for k in range(6)] + [f"eye_left_{k}" for k in range(6)]
    + [f"lip_outer_{k:02d}" for k in range(12)] + [f"lip_inner_{k}" for k in range(8)]
)
# iBUG-68 mirror pairs (image-left index, image-right index) used to check the landmark set
MIRROR_PAIRS = ([(k, 16 - k) for k in range(8)] + [(17 + k, 26 - k) for k in range(5)]
                + [(31, 35), (32, 34), (36, 45), (37, 44), (38, 43), (39, 42), (40, 47),
                   (41, 46), (48, 54), (49, 53), (50, 52), (59, 55), (58, 56), (60, 64),
                   (61, 63), (67, 65)])


def read_ict(ict_dir: Path):
    """The ICT light model arrays and the landmark vertex list."""
    npz_path, json_path = ict_dir / "ict_facemodel_light.npz", ict_dir / "vertex_indices.json"
    for path in (npz_path, json_path):
        if not path.is_file():
            raise MissingDependencyError("ICT FaceKit file not found", path=path,
                                         fix="point --ict at the ict_facekit data folder")
    data = dict(np.load(npz_path))
    landmarks = np.asarray(json.loads(json_path.read_text())["idx_to_landmark_verts"], np.int32)
    return data, landmarks


def triangulate_region(quads, n_vertices: int) -> np.ndarray:
    """(F, 3) int32 triangles of the quads/triangles (-1 padded) whose vertices are all kept."""
    valid = quads >= 0
    inside = np.all(~valid | (quads < n_vertices), axis=1)
    quads = quads[inside]
    first = quads[:, [0, 1, 2]]
    second = quads[quads[:, 3] >= 0][:, [0, 2, 3]]
    return np.concatenate([first, second]).astype(np.int32)


def boundary_loops(triangles) -> list[np.ndarray]:
    """Directed boundary edges (a, b) grouped into loops: a list of (n, 2) int arrays."""
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    keys = {tuple(e) for e in edges.tolist()}
    boundary = [e for e in edges.tolist() if (e[1], e[0]) not in keys]
    following = {a: b for a, b in boundary}
    loops, seen = [], set()
    for start in following:
        if start in seen:
            continue
        loop, a = [], start
        while a not in seen:
            seen.add(a)
            loop.append((a, following[a]))
            a = following[a]
        loops.append(np.asarray(loop, np.int32))
    return loops


def close_holes(triangles, vertices, deltas, loops):
    """Fan-fill each loop around its centroid vertex. Returns (triangles, vertices, deltas)."""
    new_vertices, new_deltas, new_faces = [vertices], [deltas], [triangles]
    next_index = vertices.shape[0]
    for loop in loops:
        ring = loop[:, 0]
        new_vertices.append(vertices[ring].mean(axis=0, keepdims=True))
        new_deltas.append(deltas[:, ring].mean(axis=1, keepdims=True))
        # Boundary edge a->b lies on an existing face, so the fan face runs b->a (same winding)
        centre = np.full(len(loop), next_index, np.int32)
        new_faces.append(np.stack([loop[:, 1], loop[:, 0], centre], axis=1))
        next_index += 1
    return (np.concatenate(new_faces), np.concatenate(new_vertices),
            np.concatenate(new_deltas, axis=1))


def check_landmarks(neutral, landmarks) -> None:
    """Raise when the 68 vertices do not have the iBUG-68 layout on the neutral mesh."""
    p = neutral[landmarks]
    tol = 0.05  # cm
    problems = []
    for left, right in MIRROR_PAIRS:
        mirrored = p[right] * np.array([-1.0, 1.0, 1.0])
        if np.linalg.norm(p[left] - mirrored) > tol or p[left, 0] >= 0:
            problems.append(f"pair {left}/{right}")
    if not np.all(np.diff(p[0:9, 0]) > 0):
        problems.append("jaw not ordered image-left to right")
    if not (p[8, 1] < p[57, 1] < p[51, 1] < p[33, 1] < p[30, 1] < p[27, 1] < p[21, 1]):
        problems.append("midline landmarks not ordered chin to brow")
    if not (p[36, 0] < p[39, 0] < 0 < p[42, 0] < p[45, 0]):
        problems.append("eye corners")
    if problems:
        raise ValueError("ICT landmark set is not in iBUG-68 order: " + ", ".join(problems))


def build_arrays(data, landmarks, identity_modes: int) -> dict:
    """The arrays of the shipped model, as a name -> ndarray dict."""
    neutral = data["neutral_vertices"].astype(np.float64)[:HEAD_NECK_VERTICES]
    triangles = triangulate_region(data["faces"], HEAD_NECK_VERTICES)
    expression_all = data["expression_deltas"][:, :HEAD_NECK_VERTICES]
    moving = np.abs(expression_all).max(axis=(1, 2)) > MIN_EXPRESSION_MOTION
    identity = data["identity_deltas"][:identity_modes, :HEAD_NECK_VERTICES]
    deltas = np.concatenate([identity, expression_all[moving]]).astype(np.float64)
    loops = boundary_loops(triangles)
    neck = int(np.argmin([neutral[loop[:, 0], 1].mean() for loop in loops]))
    holes = [loop for k, loop in enumerate(loops) if k != neck]
    triangles, vertices, deltas = close_holes(triangles, neutral, deltas, holes)
    check_landmarks(vertices, landmarks)
    face_region = np.zeros(vertices.shape[0], bool)
    face_region[:FACE_VERTICES] = True
    face_region[HEAD_NECK_VERTICES:] = True
    return {
        "format_version": np.array(FORMAT_VERSION, np.int32),
        "neutral_vertices": vertices.astype(np.float32),
        "triangles": triangles.astype(np.int32),
        "face_region": face_region,
        "identity_basis": deltas[:identity_modes].astype(np.float16),
        "identity_names": data["identity_names"][:identity_modes].astype(str),
        "expression_basis": deltas[identity_modes:].astype(np.float16),
        "expression_names": data["expression_names"][moving].astype(str),
        "landmark_indices": landmarks,
        "landmark_names": np.array(LANDMARK_NAMES),
        "units": np.array("cm"),
        "license": np.array(ICT_LICENSE),
        "source": np.array("ICT-VGL/ICT-FaceKit FaceXModel (commit da5f95a607f5), "
                           "Face Model Light; vertices 0..11247, holes fan-filled"),
    }


def write_npz(path: Path, arrays: dict) -> str:
    """Write a deterministic compressed npz (fixed member timestamps); return its sha256."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, member.getvalue(), compresslevel=9)
    payload = buffer.getvalue()
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".npz.tmp")
    temporary.write_bytes(payload)
    temporary.replace(path)
    return hashlib.sha256(payload).hexdigest()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ict", type=Path, default=DEFAULT_ICT_DIR)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--identity-modes", type=int, default=DEFAULT_IDENTITY_MODES)
    args = parser.parse_args(argv)
    data, landmarks = read_ict(args.ict.resolve())
    arrays = build_arrays(data, landmarks, args.identity_modes)
    digest = write_npz(args.out, arrays)
    print(json.dumps({"file": args.out.name, "sha256": digest,
                      "bytes": args.out.stat().st_size,
                      "vertices": int(arrays["neutral_vertices"].shape[0]),
                      "triangles": int(arrays["triangles"].shape[0]),
                      "identity_modes": int(arrays["identity_basis"].shape[0]),
                      "expression_modes": int(arrays["expression_basis"].shape[0])}))


if __name__ == "__main__":
    main()
