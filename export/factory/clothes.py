"""Clothes, shoes and hair bound to the body through MakeHuman `.mhclo` files.

`.mhclo` format (read from the files): header lines `key value...` (`name`, `obj_file`,
`x_scale i j ref`, `y_scale`, `z_scale`, ...), then after `verts 0` one line per clothing vertex:
either `a b c wa wb wc dx dy dz` (three base-mesh vertices, barycentric-like weights, an offset)
or a single `a` (sits on base vertex a); then optionally `delete_verts` followed by ids and
ranges `i - j` of body vertices the garment hides.

Fitting (rest pose, any body shape): p = sum_k w_k v[a_k] + d * s with the per-axis scale
s_x = |v[i].x - v[j].x| / ref (same for y, z), so garments follow the shape. Posing: each garment
vertex inherits skin weights W_cloth = B W_body (B holds the same w_k), so it follows the pose
by the same linear-blend skinning as the body under it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from relightcli.errors import InputError

from . import assets
from .makehuman import MH_UNIT_M, ObjMesh, read_obj, read_weights

# Catalogue of wearable items in the assets archive, by slot.
SUITS = ("female_casualsuit01", "female_casualsuit02", "female_elegantsuit01",
         "male_casualsuit01", "male_casualsuit02", "male_casualsuit03", "male_casualsuit04",
         "male_casualsuit05", "male_elegantsuit01", "male_worksuit01")
SHOES = ("shoes01", "shoes02", "shoes03", "shoes04", "shoes05", "shoes06")
HAIR = ("bob01", "bob02", "long01", "ponytail01", "short01", "short02", "short03", "short04")
HATS = ("fedora01/fedora", "fedora01/fedora_cocked")


@dataclass(frozen=True)
class Garment:
    """One bound item.

    mesh: its triangulated OBJ (metres). ids: (N, 3) int64 base-mesh vertices; weights: (N, 3)
    float64; offsets: (N, 3) float64 m; scale_refs: {"x"|"y"|"z": (i, j, ref_m)};
    delete_verts: (M,) int64 base-mesh vertices hidden under the garment.
    weights_file: the garment's own `.mhw` skin weights (shoes have them), or None.
    """

    name: str
    mesh: ObjMesh
    ids: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    scale_refs: dict
    delete_verts: np.ndarray
    weights_file: Path | None = None


def _parse_delete(tokens: list[str]) -> np.ndarray:
    ids, k = [], 0
    while k < len(tokens):
        if k + 2 < len(tokens) and tokens[k + 1] == "-":
            ids.extend(range(int(tokens[k]), int(tokens[k + 2]) + 1))
            k += 3
        else:
            ids.append(int(tokens[k]))
            k += 1
    return np.asarray(ids, dtype=np.int64)


def _binding_row(tokens: list[str]) -> tuple[list[int], list[float], list[float]]:
    if len(tokens) == 1:
        a = int(tokens[0])
        return [a, a, a], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    return ([int(t) for t in tokens[:3]], [float(t) for t in tokens[3:6]],
            [float(t) for t in tokens[6:9]])


@functools.lru_cache(maxsize=64)
def read_mhclo(path: str | Path) -> Garment:
    """Read a `.mhclo` binding and the OBJ it names (cached per path)."""
    path = Path(path)
    header, rows, delete_tokens, section = {}, [], [], "header"
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if tokens[0] == "verts":
            section = "verts"
        elif tokens[0] == "delete_verts":
            section = "delete"
        elif section == "delete":
            delete_tokens += tokens
        elif section == "verts" and tokens[0].lstrip("-").isdigit():
            rows.append(_binding_row(tokens))
        else:
            header[tokens[0]] = tokens[1:]
    if "obj_file" not in header or not rows:
        raise InputError("mhclo file lacks obj_file or vertex bindings", path=path)
    mesh = read_obj(path.parent / header["obj_file"][0])
    if len(mesh.vertices) != len(rows):
        raise InputError(f"{len(rows)} bindings for {len(mesh.vertices)} OBJ vertices", path=path)
    scale_refs = {axis: (int(header[f"{axis}_scale"][0]), int(header[f"{axis}_scale"][1]),
                         float(header[f"{axis}_scale"][2]) * MH_UNIT_M)
                  for axis in "xyz" if f"{axis}_scale" in header}
    ids, weights, offsets = (np.asarray(col) for col in zip(*rows))
    return Garment(name=header.get("name", [path.stem])[0], mesh=mesh, ids=ids.astype(np.int64),
                   weights=weights.astype(np.float64), offsets=offsets * MH_UNIT_M,
                   scale_refs=scale_refs, delete_verts=_parse_delete(delete_tokens),
                   weights_file=path.parent / header["vertexboneweights_file"][0]
                   if "vertexboneweights_file" in header else None)


def garment_path(slot_item: str) -> Path:
    """`.mhclo` path of a catalogue item, e.g. "clothes/shoes01" or "hair/bob01"."""
    folder, _, item = slot_item.partition("/")
    sub = item if "/" in item else f"{item}/{item}"
    return assets.asset_path(f"{folder}/{sub}.mhclo")


def offset_scale(garment: Garment, body_vertices: np.ndarray) -> np.ndarray:
    """Per-axis offset scale (3,) for a shaped body: |v_i - v_j| along the axis / reference."""
    scale = np.ones(3)
    for axis, (i, j, ref) in garment.scale_refs.items():
        k = "xyz".index(axis)
        scale[k] = abs(body_vertices[i, k] - body_vertices[j, k]) / ref
    return scale


def fit_garment(garment: Garment, body_vertices: np.ndarray) -> np.ndarray:
    """Garment vertices (N, 3) float64 m on a rest-pose body `body_vertices` (19158, 3)."""
    anchors = np.einsum("nk,nkd->nd", garment.weights, body_vertices[garment.ids])
    return anchors + garment.offsets * offset_scale(garment, body_vertices)


def binding_matrix(garment: Garment, n_body_vertices: int) -> sp.csr_matrix:
    """(N, V) sparse matrix B with B @ body_vertices = the garment's anchor points."""
    n = len(garment.ids)
    return sp.csr_matrix((garment.weights.ravel(), (np.repeat(np.arange(n), 3),
                                                    garment.ids.ravel())),
                         shape=(n, n_body_vertices))


def garment_skin_weights(garment: Garment, body_weights: sp.spmatrix,
                         bone_names: tuple[str, ...]) -> sp.csr_matrix:
    """Skin weights (N, B) of the garment vertices, rows summing to 1.

    The garment's own `.mhw` when it has one (shoes: rigid soles that must not bend with the
    toes), else its anchors' blended body weights B W_body (MakeHuman's transfer).
    """
    if garment.weights_file is not None:
        return read_weights(garment.weights_file, bone_names, len(garment.ids))
    blended = sp.csr_matrix(binding_matrix(garment, body_weights.shape[0]) @ body_weights)
    return sp.csr_matrix(sp.diags(1.0 / np.asarray(blended.sum(axis=1)).ravel()) @ blended)
