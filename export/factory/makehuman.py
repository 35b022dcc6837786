"""Readers for the MakeHuman formats we use (written from the files themselves).

Units: MakeHuman stores geometry in decimetres; every reader here returns metres
(`MH_UNIT_M`). Frame: the hm08 mesh is already +Y up, facing +Z, which is the project's world
frame (DESIGN.md). BVH files are Z-up with the body facing -Y; `BVH_TO_MESH` maps them.

Formats
- `.obj`: `v`, `vt`, `g` and `f a/ta b/tb ...` lines; polygons are fanned into triangles.
- `.target`: `index dx dy dz` lines (sparse vertex offsets), `#` comments.
- `.mhskel`: JSON; `joints` maps a joint name to base-mesh vertex ids (its position is their
  mean), `bones` maps a bone to its `head`/`tail` joints and `parent`.
- `.mhw`: JSON; `weights` maps a bone to `[[vertex, weight], ...]`.
- `.bvh`: standard BVH hierarchy + one MOTION frame of Euler angles in degrees.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from relightcli.errors import InputError

MH_UNIT_M = 0.1
# BVH (x, y, z), Z up and facing -Y  ->  mesh (x, z, -y), Y up and facing +Z.
BVH_TO_MESH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class ObjMesh:
    """A triangulated OBJ mesh.

    vertices: (V, 3) float64, metres. faces: (F, 3) int64 vertex ids. uvs: (F, 3, 2) float32
    per-corner texture coordinates (OBJ convention, v = 0 at the bottom of the image).
    face_group: (F,) int64 index into `group_names` (the `g` line each face came under).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    face_group: np.ndarray
    group_names: tuple[str, ...]


def _fan(polygon: list[int]) -> list[tuple[int, int, int]]:
    return [(polygon[0], polygon[k], polygon[k + 1]) for k in range(1, len(polygon) - 1)]


def read_obj(path: str | Path) -> ObjMesh:
    """Read an OBJ file (MakeHuman base mesh, clothes, hair) into metres, triangulated."""
    verts, texcoords, faces, face_uv, groups, face_group = [], [], [], [], [], []
    group = 0
    with open(path, encoding="utf-8", errors="replace") as stream:
        for line in stream:
            tokens = line.split()
            if not tokens:
                continue
            if tokens[0] == "v":
                verts.append([float(t) for t in tokens[1:4]])
            elif tokens[0] == "vt":
                texcoords.append([float(t) for t in tokens[1:3]])
            elif tokens[0] == "g":
                groups.append(tokens[1] if len(tokens) > 1 else "")
                group = len(groups) - 1
            elif tokens[0] == "f":
                corners = [t.split("/") for t in tokens[1:]]
                vids = [int(c[0]) - 1 for c in corners]
                tids = [int(c[1]) - 1 if len(c) > 1 and c[1] else -1 for c in corners]
                faces += _fan(vids)
                face_uv += _fan(tids)
                face_group += [group] * (len(vids) - 2)
    if not verts or not faces:
        raise InputError("OBJ file has no vertices or faces", path=path)
    uv_table = np.array(texcoords + [[0.0, 0.0]], dtype=np.float32)  # id -1 -> (0, 0)
    return ObjMesh(
        vertices=np.asarray(verts, dtype=np.float64) * MH_UNIT_M,
        faces=np.asarray(faces, dtype=np.int64),
        uvs=uv_table[np.asarray(face_uv, dtype=np.int64)],
        face_group=np.asarray(face_group, dtype=np.int64),
        group_names=tuple(groups) if groups else ("",),
    )


def _numeric_rows(path: str | Path, width: int) -> np.ndarray:
    with open(path, encoding="utf-8", errors="replace") as stream:
        text = "".join(line for line in stream
                       if line.strip() and not line.lstrip().startswith("#"))
    values = np.array(text.split(), dtype=np.float64)
    if values.size % width:
        raise InputError(f"expected rows of {width} numbers", path=path)
    return values.reshape(-1, width)


@functools.lru_cache(maxsize=256)
def read_target(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a `.target` morph: (ids (K,) int64, offsets (K, 3) float64 in metres).

    An empty target (MakeHuman uses them for the neutral corner of a blend) gives K = 0.
    """
    rows = _numeric_rows(path, 4)
    return rows[:, 0].astype(np.int64), rows[:, 1:] * MH_UNIT_M


@dataclass(frozen=True)
class Skeleton:
    """The MakeHuman rig, bones in parent-before-child order.

    names: B bone names. parents: (B,) int64, -1 for the root.
    head_vertices / tail_vertices: per bone, the base-mesh vertex ids whose mean is the joint.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    head_vertices: tuple[np.ndarray, ...]
    tail_vertices: tuple[np.ndarray, ...]

    def joint_positions(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bone heads and tails (B, 3) float64 for a shaped mesh `vertices` (V, 3)."""
        heads = np.stack([vertices[ids].mean(axis=0) for ids in self.head_vertices])
        tails = np.stack([vertices[ids].mean(axis=0) for ids in self.tail_vertices])
        return heads, tails


def _topological_order(parent_of: dict[str, str | None]) -> list[str]:
    order, placed = [], set()
    pending = sorted(parent_of)
    while pending:
        ready = [b for b in pending if parent_of[b] is None or parent_of[b] in placed]
        if not ready:
            raise InputError(f"rig has a cycle or a missing parent among {pending[:5]}")
        order += ready
        placed.update(ready)
        pending = [b for b in pending if b not in placed]
    return order


@functools.lru_cache(maxsize=4)
def read_skeleton(path: str | Path) -> Skeleton:
    """Read a `.mhskel` rig."""
    with open(path, encoding="utf-8") as stream:
        data = json.load(stream)
    bones, joints = data["bones"], data["joints"]
    order = _topological_order({name: bone["parent"] for name, bone in bones.items()})
    index = {name: k for k, name in enumerate(order)}
    parents = np.array([index[bones[b]["parent"]] if bones[b]["parent"] else -1 for b in order])
    return Skeleton(
        names=tuple(order),
        parents=parents,
        head_vertices=tuple(np.asarray(joints[bones[b]["head"]], dtype=np.int64) for b in order),
        tail_vertices=tuple(np.asarray(joints[bones[b]["tail"]], dtype=np.int64) for b in order),
    )


def read_weights(path: str | Path, bone_names: tuple[str, ...], n_vertices: int) -> sp.csr_matrix:
    """Read `.mhw` skin weights as a (V, B) float64 sparse matrix whose rows sum to 1.

    Upstream rows are not normalised (sums 0.3-1.7); a vertex with no weight at all is given to
    the first bone (the root) so that it stays rigid rather than collapsing to the origin.
    """
    with open(path, encoding="utf-8") as stream:
        weights = json.load(stream)["weights"]
    index = {name: k for k, name in enumerate(bone_names)}
    rows, cols, vals = [], [], []
    for bone, pairs in weights.items():
        if bone not in index or not pairs:
            continue
        pairs = np.asarray(pairs, dtype=np.float64)
        rows.append(pairs[:, 0].astype(np.int64))
        cols.append(np.full(len(pairs), index[bone]))
        vals.append(pairs[:, 1])
    matrix = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(n_vertices, len(bone_names)))
    totals = np.asarray(matrix.sum(axis=1)).ravel()
    orphans = np.flatnonzero(totals <= 0)
    if orphans.size:
        matrix = matrix + sp.csr_matrix(
            (np.ones(orphans.size), (orphans, np.zeros(orphans.size, dtype=np.int64))),
            shape=matrix.shape)
        totals[orphans] = 1.0
    return sp.diags(1.0 / totals) @ matrix


@dataclass(frozen=True)
class BvhPose:
    """First frame of a BVH file.

    names: J joint names; parents: (J,) int64, -1 for the root; offsets: (J, 3) float64 in the
    file's units and frame; rotations: (J, 3, 3) float64 local rotation matrices in the BVH frame
    (channel order honoured: for `Xrotation Yrotation Zrotation`, R = Rx @ Ry @ Rz).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    rotations: np.ndarray


def axis_rotation(axis: str, degrees: np.ndarray | float) -> np.ndarray:
    """Rotation matrix/matrices (..., 3, 3) about the x, y or z axis, right-handed."""
    a = np.radians(np.asarray(degrees, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    k = 3 - i - j
    m = np.zeros(a.shape + (3, 3))
    m[..., k, k] = one
    m[..., i, i], m[..., i, j], m[..., j, i], m[..., j, j] = c, -s, s, c
    return m + zero[..., None, None]


def _parse_hierarchy(tokens: list[str]) -> tuple[list, int]:
    joints, stack, pos = [], [], 0
    while tokens[pos] != "MOTION":
        tok = tokens[pos]
        if tok in ("ROOT", "JOINT"):
            joints.append({"name": tokens[pos + 1], "parent": stack[-1] if stack else -1,
                           "channels": [], "offset": None})
            pos += 2
        elif tok == "End":  # `End Site { OFFSET x y z }`: 8 tokens, no joint
            pos += 8
        elif tok == "{":
            stack.append(len(joints) - 1)
            pos += 1
        elif tok == "}":
            stack.pop()
            pos += 1
        elif tok == "OFFSET":
            joints[-1]["offset"] = [float(t) for t in tokens[pos + 1:pos + 4]]
            pos += 4
        elif tok == "CHANNELS":
            count = int(tokens[pos + 1])
            joints[-1]["channels"] = tokens[pos + 2:pos + 2 + count]
            pos += 2 + count
        else:
            pos += 1
    return joints, pos


def read_bvh(path: str | Path) -> BvhPose:
    """Read the hierarchy and the first frame of a BVH file."""
    tokens = Path(path).read_text(encoding="utf-8", errors="replace").split()
    try:
        joints, pos = _parse_hierarchy(tokens)
        frame_start = tokens.index("Time:", pos) + 2
        n_values = sum(len(j["channels"]) for j in joints)
        values = np.array(tokens[frame_start:frame_start + n_values], dtype=np.float64)
    except (ValueError, IndexError) as exc:
        raise InputError(f"not a readable BVH file ({exc})", path=path) from exc
    if values.size != n_values:
        raise InputError("BVH motion frame is shorter than its channel list", path=path)
    rotations, cursor = [], 0
    for joint in joints:
        rot = np.eye(3)
        for channel in joint["channels"]:
            if channel.endswith("rotation"):
                rot = rot @ axis_rotation(channel[0].lower(), values[cursor])
            cursor += 1
        rotations.append(rot)
    return BvhPose(
        names=tuple(j["name"] for j in joints),
        parents=np.array([j["parent"] for j in joints], dtype=np.int64),
        offsets=np.array([j["offset"] for j in joints], dtype=np.float64),
        rotations=np.stack(rotations),
    )
