"""`build_person(seed, split)`: one posed, clothed, textured MakeHuman body, deterministic.

Output units and frame: metres, +Y up, facing +Z (toward the camera), feet (lowest rendered
point) at y = 0, the root joint above x = z = 0.

Albedo representation: one UV texture atlas per person (tiles stacked vertically: skin, eyes,
suit, shoes, hair[, hat]) plus per-corner UVs, so a renderer interpolates the UV at a hit point
(barycentrics) and looks the albedo up (`albedo.sample_texture`); `vertex_albedo` (the atlas
sampled at each vertex) is there for renderers that prefer per-vertex colour.

Splits (deterministic, disjoint): poses, suits, shoes, hair and hats are each ordered by the
SHA-256 of "relightcli-split:<name>"; the first `n_test` go to test, the next `n_val` to val,
the rest to train (counts in SPLIT_COUNTS). Body shapes, skin tones and textures come from the
random stream SeedSequence([seed, split index]), so a seed gives different people in different
splits and the same person every time.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sp

from relightcli.errors import UsageError
from relightcli.io.images import read_image

from . import albedo, assets, clothes, shape, skinning
from .makehuman import ObjMesh, Skeleton, read_bvh, read_obj, read_skeleton, read_weights

SPLITS = ("train", "val", "test")
PART_NAMES = ("skin", "cloth", "hair", "eyes")
TILE = 512
POSES = ("rest", "benchmark", "tpose", "fight01", "fight02", "fight04", "fly01", "fly02", "gym01",
         "sit01", "standing01", "standing02", "standing03", "standing04", "standing06")
CORE_POSES = ("benchmark", "tpose")
CATALOGUE = {"pose": POSES,
             "suit_female": tuple(s for s in clothes.SUITS if s.startswith("female")),
             "suit_male": tuple(s for s in clothes.SUITS if s.startswith("male")),
             "shoes": clothes.SHOES, "hair": clothes.HAIR, "hat": clothes.HATS}
# (n_test, n_val) per category; suits are split per gender so train keeps both kinds.
SPLIT_COUNTS = {"pose": (3, 2), "suit_female": (1, 0), "suit_male": (1, 1), "shoes": (1, 1),
                "hair": (2, 1), "hat": (1, 0)}
HAT_PROBABILITY = 0.15
EYES = "eyes/low-poly/low-poly.mhclo"


@dataclass(frozen=True)
class Person:
    """A posed, clothed person ready to render.

    vertices: (V, 3) float32 m. faces: (F, 3) int32. face_uv: (F, 3, 2) float32 atlas UVs
    (v = 0 at the bottom row of `texture`). texture: (H, W, 3) float32 linear albedo in [0, 1].
    vertex_albedo: (V, 3) float32 linear in [0, 1]. face_part: (F,) uint8 index into PART_NAMES.
    face_vertex_ids: (K,) int64 vertices of the facial region (for face boxes).
    metadata: seed, split, shape parameters, stature, pose, outfit, skin tone, hair colour,
    cloth patterns. joints: (B, 3) float32 m, the posed bone heads in the vertices' frame
    (the rig's bone order, `base_model().skeleton.names`): the true skeleton a fit is
    measured against.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_uv: np.ndarray
    texture: np.ndarray
    vertex_albedo: np.ndarray
    face_part: np.ndarray
    face_vertex_ids: np.ndarray
    metadata: dict = field(default_factory=dict)
    joints: np.ndarray | None = None


@dataclass(frozen=True)
class BaseModel:
    """The hm08 mesh with its rig: mesh (all 19,158 vertices, helpers included), skeleton,
    weights (V, B) sparse, body_faces (Fb,) ids of the faces in group `body`."""

    mesh: ObjMesh
    skeleton: Skeleton
    weights: sp.csr_matrix
    body_faces: np.ndarray


@functools.lru_cache(maxsize=1)
def base_model() -> BaseModel:
    """Load (once per process) the base mesh, the default rig and its weights."""
    mesh = read_obj(assets.base_obj_path())
    skeleton = read_skeleton(assets.core_path("rigs/default.mhskel"))
    weights = read_weights(assets.core_path("rigs/default_weights.mhw"), skeleton.names,
                           len(mesh.vertices))
    body_faces = np.flatnonzero(mesh.face_group == mesh.group_names.index("body"))
    return BaseModel(mesh=mesh, skeleton=skeleton, weights=weights, body_faces=body_faces)


def split_items(items: tuple[str, ...], n_test: int, n_val: int) -> dict[str, tuple[str, ...]]:
    """Disjoint train/val/test lists: items ordered by SHA-256 of their name (see module doc)."""
    def key(name: str) -> str:
        return hashlib.sha256(f"relightcli-split:{name}".encode()).hexdigest()

    order = sorted(items, key=key)
    return {"test": tuple(sorted(order[:n_test])),
            "val": tuple(sorted(order[n_test:n_test + n_val])),
            "train": tuple(sorted(order[n_test + n_val:]))}


def splits() -> dict[str, dict[str, tuple[str, ...]]]:
    """category ("pose", "suit_female", "suit_male", "shoes", "hair", "hat") -> split -> items."""
    return {cat: split_items(CATALOGUE[cat], *SPLIT_COUNTS[cat]) for cat in CATALOGUE}


def pose_rotations(name: str, skeleton: Skeleton) -> np.ndarray:
    """Local bone rotations (B, 3, 3) of a catalogue pose ("rest" gives identities); a fresh
    array each call (a mixed pose reads up to five poses a person: each file is read once)."""
    return _pose_rotations(name, tuple(skeleton.names)).copy()


@functools.lru_cache(maxsize=64)
def _pose_rotations(name: str, bone_names: tuple[str, ...]) -> np.ndarray:
    if name == "rest":
        return np.tile(np.eye(3), (len(bone_names), 1, 1))
    path = assets.core_path(f"poses/{name}.bvh") if name in CORE_POSES else \
        assets.asset_path(f"poses/{name}.bvh")
    return skinning.local_rotations_from_bvh(read_bvh(path), bone_names)


def choose_outfit(rng: np.random.Generator, split: str, gender: float) -> dict[str, str]:
    """slot -> item path ("clothes/...", "hair/..."): a suit (80 % matching the gender when the
    split offers one), shoes, hair, sometimes a hat."""
    lists = {cat: items[split] for cat, items in splits().items()}
    matching = list(lists["suit_female" if gender < 0.5 else "suit_male"])
    suits = matching if matching and rng.random() < 0.8 else \
        list(lists["suit_female"] + lists["suit_male"])
    outfit = {"suit": "clothes/" + str(rng.choice(suits)),
              "shoes": "clothes/" + str(rng.choice(lists["shoes"])),
              "hair": "hair/" + str(rng.choice(lists["hair"]))}
    if lists["hat"] and rng.random() < HAT_PROBABILITY:
        outfit["hat"] = "clothes/" + str(rng.choice(lists["hat"]))
    return outfit


def _check_request(seed: int, split: str) -> None:
    if split not in SPLITS:
        raise UsageError(f"unknown split {split!r}", fix=f"use one of {', '.join(SPLITS)}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UsageError(f"seed must be a non-negative integer, got {seed!r}")


@dataclass
class _Part:
    """One mesh piece during assembly: rest vertices (N, 3), skin weights (N, B), faces (F, 3)
    local ids, corner UVs (F, 3, 2) in the piece's own [0, 1] UV space, a part label, a tile."""

    rest: np.ndarray
    weights: sp.spmatrix
    faces: np.ndarray
    uvs: np.ndarray
    part: int
    tile: np.ndarray


def sample_body(rng: np.random.Generator, base: BaseModel) -> tuple[shape.ShapeParams, np.ndarray]:
    """Random shape whose standing height follows `shape.sample_stature`; returns the params
    and the shaped rest vertices (19158, 3) m."""
    params = shape.sample_shape(rng)
    body_ids = np.unique(base.mesh.faces[base.body_faces])
    target = shape.sample_stature(rng, params.gender)
    height = shape.solve_height_param(params, base.mesh.vertices, body_ids, target)
    params = shape.ShapeParams(**{**params.as_dict(), "height": height, "race": params.race,
                                  "details": params.details})
    return params, shape.apply_targets(base.mesh.vertices, shape.all_target_weights(params))


def face_region(base: BaseModel, shaped: np.ndarray) -> np.ndarray:
    """Boolean mask (19158,) of body vertices on the face: mostly skinned to the head bone or
    its descendants (jaw, eyes, facial muscles) and in front of the head joint."""
    names, parents = base.skeleton.names, base.skeleton.parents
    in_head = np.zeros(len(names), dtype=bool)
    in_head[names.index("head")] = True
    for b, p in enumerate(parents):  # parents precede children
        in_head[b] |= p >= 0 and in_head[p]
    head_weight = np.asarray(base.weights[:, in_head].sum(axis=1)).ravel()
    heads, _ = base.skeleton.joint_positions(shaped)
    on_body = np.zeros(len(shaped), dtype=bool)
    on_body[np.unique(base.mesh.faces[base.body_faces])] = True
    front = shaped[:, 2] > heads[names.index("head"), 2] + 0.02
    return on_body & (head_weight > 0.5) & front


def _visible_body_faces(base: BaseModel, hidden: np.ndarray) -> np.ndarray:
    # A body face disappears when all its corners are hidden by some garment (delete_verts).
    faces = base.mesh.faces[base.body_faces]
    mask = np.zeros(len(base.mesh.vertices), dtype=bool)
    mask[hidden] = True
    return base.body_faces[~mask[faces].all(axis=1)]


def _chest_uv(garment: clothes.Garment, rest: np.ndarray, chest: np.ndarray) -> tuple[float, float]:
    # UV of the garment vertex closest to the point in front of the sternum: where logos go.
    near = np.abs(rest[:, 0] - chest[0]) + np.abs(rest[:, 1] - chest[1])
    candidates = np.flatnonzero(near < 0.06)
    vertex = candidates[np.argmax(rest[candidates, 2])] if candidates.size else int(np.argmin(near))
    corners = np.argwhere(garment.mesh.faces == vertex)
    return tuple(float(x) for x in garment.mesh.uvs[corners[0, 0], corners[0, 1]])


@functools.lru_cache(maxsize=1)
def _eye_tile() -> np.ndarray:
    image = read_image(assets.core_path("eyes/materials/brown_eye.png"))
    return cv2.resize(image.rgb, (TILE, TILE), interpolation=cv2.INTER_AREA).clip(0, 1)


def _garment_part(name: str, base: BaseModel, shaped: np.ndarray, part: int,
                  tile: np.ndarray) -> tuple[_Part, clothes.Garment]:
    garment = clothes.read_mhclo(clothes.garment_path(name) if not name.endswith(".mhclo")
                                 else assets.core_path(name))
    rest = clothes.fit_garment(garment, shaped)
    weights = clothes.garment_skin_weights(garment, base.weights, base.skeleton.names)
    return _Part(rest, weights, garment.mesh.faces, garment.mesh.uvs, part, tile), garment


def _atlas(parts: list[_Part]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Stack the parts' tiles top to bottom; return the atlas (n T, T, 3) and each part's UVs
    remapped into it (clamped half a texel inside the tile so bilinear lookups never bleed)."""
    n = len(parts)
    texture = np.concatenate([p.tile for p in parts], axis=0)
    margin = 0.5 / TILE
    remapped = []
    for k, p in enumerate(parts):
        uv = np.clip(p.uvs, margin, 1.0 - margin)
        remapped.append(np.stack([uv[..., 0], (n - 1 - k + uv[..., 1]) / n], axis=-1))
    return texture, remapped


def _vertex_albedo(texture: np.ndarray, faces: np.ndarray, face_uv: np.ndarray,
                   n_vertices: int) -> np.ndarray:
    # Average of the texture at each corner UV a vertex has (seams give several).
    colours = albedo.sample_texture(texture, face_uv.reshape(-1, 2))
    total = np.zeros((n_vertices, 3))
    np.add.at(total, faces.ravel(), colours)
    count = np.bincount(faces.ravel(), minlength=n_vertices)[:, None]
    return (total / np.maximum(count, 1)).astype(np.float32)


def _outfit_parts(rng: np.random.Generator, base: BaseModel, shaped: np.ndarray,
                  outfit: dict[str, str], metadata: dict) -> tuple[list[_Part], list[np.ndarray]]:
    """Fit and texture each worn item; returns the parts and the body vertices they hide.
    Records hair colour and cloth patterns in `metadata`."""
    parts, hidden = [], []
    heads, _ = base.skeleton.joint_positions(shaped)
    chest = heads[base.skeleton.names.index("spine02")]
    for slot, item in outfit.items():
        if slot == "hair":
            name, colour = albedo.sample_hair_colour(rng, metadata["shape"]["age"])
            metadata["hair_colour"] = name
            tile, label = albedo.hair_texture(rng, TILE, colour), 2
        else:
            tile, metadata["patterns"][slot] = albedo.cloth_texture(rng, TILE)
            label = 1
        part, garment = _garment_part(item, base, shaped, label, tile)
        if slot == "suit" and rng.random() < 0.5:
            albedo.paint_logo(rng, tile, _chest_uv(garment, part.rest, chest))
            metadata["patterns"]["logo"] = True
        parts.append(part)
        hidden.append(garment.delete_verts)
    return parts, hidden


def _pose_parts(parts: list[_Part], base: BaseModel, shaped: np.ndarray, rotations: np.ndarray
                ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    heads, _ = base.skeleton.joint_positions(shaped)
    transforms = skinning.bone_transforms(base.skeleton, heads, rotations)
    posed = [skinning.skin_vertices(p.rest, p.weights, transforms) for p in parts]
    joints = np.einsum("bij,bj->bi", transforms, np.c_[heads, np.ones(len(heads))])[:, :3]
    return posed, joints[0], joints


def build_person(seed: int, split: str, pose_variety: float = 0.0) -> Person:
    """A random posed, clothed, textured person; the same (seed, split, pose_variety) gives the
    same person.

    split: "train", "val" or "test": pose, suit, shoes, hair and hat come from that split's list.
    pose_variety: in [0, 1], how far the pose may leave its catalogue pose (mixed_pose); 0 keeps
    the catalogue pose with small perturbations (the people of every dataset made before it).
    """
    _check_request(seed, split)
    base = base_model()
    r_shape, r_pose, r_outfit, r_albedo, r_mix = _streams(seed, split)
    params, shaped, pose, rotations, mix = _shape_and_pose(base, split, r_shape, r_pose, r_mix, pose_variety)
    outfit = choose_outfit(r_outfit, split, params.gender)
    tone_t = float(r_albedo.random())
    metadata = {"seed": int(seed), "split": split, "shape": params.as_dict(),
                "stature_m": shape.stature(shaped, np.unique(base.mesh.faces[base.body_faces])),
                "pose": pose, "outfit": outfit, "skin_tone": tone_t, "patterns": {}}
    if pose_variety > 0:
        metadata.update(pose_variety=float(pose_variety), pose_mix=mix)
    skin = albedo.skin_texture(r_albedo, TILE, albedo.skin_tone(tone_t))
    garments, hidden = _outfit_parts(r_albedo, base, shaped, outfit, metadata)
    eyes, _ = _garment_part(EYES, base, shaped, 3, _eye_tile())
    visible = _visible_body_faces(base, np.concatenate(hidden))
    body = _Part(shaped, base.weights, base.mesh.faces[visible], base.mesh.uvs[visible], 0, skin)
    parts = [body, eyes] + garments
    posed, root, joints = _pose_parts(parts, base, shaped, rotations)
    return _assemble(parts, posed, root, face_region(base, shaped), metadata, joints)


@dataclass(frozen=True)
class NakedBody:
    """The body of build_person(seed, split) without clothes, hair or eyes, posed and placed as
    that person is (the same joints): what a perfect body fit would find under the clothes.
    vertices (V, 3) float32 m, every base-mesh vertex posed (the body's are 0..n-1, the rest
    are helpers no face uses); faces (F, 3) int32, the body's; shaped (V, 3) the rest
    vertices; transforms (B, 3, 4) the bones' affines from rest to placed."""

    vertices: np.ndarray
    faces: np.ndarray
    shaped: np.ndarray
    transforms: np.ndarray


def naked_body(seed: int, split: str, pose_variety: float = 0.0, placed: bool = True) -> NakedBody:
    """The person's body under the clothes (bench/oracles.py's `true body`). `placed` False: about
    the skeleton's own origin instead of where the clothed person stands (which takes building
    that person, ~0.7 s), for what is measured relative to the body anyway (its landmarks
    about the hips)."""
    _check_request(seed, split)
    base = base_model()
    r_shape, r_pose, _, _, r_mix = _streams(seed, split)
    _, shaped, _, rotations, _ = _shape_and_pose(base, split, r_shape, r_pose, r_mix, pose_variety)
    heads, _ = base.skeleton.joint_positions(shaped)
    transforms = skinning.bone_transforms(base.skeleton, heads, rotations)
    joints = np.einsum("bij,bj->bi", transforms, np.c_[heads, np.ones(len(heads))])[:, :3]
    if placed:  # the clothed person's feet set y = 0
        transforms = transforms.copy()
        transforms[:, :, 3] -= joints[0] - build_person(seed, split, pose_variety).joints[0]
    vertices = skinning.skin_vertices(shaped, base.weights, transforms)
    return NakedBody(vertices.astype(np.float32), base.mesh.faces[base.body_faces].astype(np.int32), shaped, transforms)


def _streams(seed: int, split: str) -> list[np.random.Generator]:
    """The person's five random streams: shape, pose, outfit, albedo, pose mixing (the first
    four are what they were before the fifth was added: children of a SeedSequence depend on
    their index only)."""
    streams = np.random.SeedSequence([int(seed), SPLITS.index(split)]).spawn(5)
    return [np.random.default_rng(s) for s in streams]


def _shape_and_pose(base: BaseModel, split: str, r_shape, r_pose, r_mix, pose_variety: float = 0.0) -> tuple:
    """(shape params, shaped rest vertices, pose name, perturbed bone rotations, the mix)."""
    params, shaped = sample_body(r_shape, base)
    pose = str(r_pose.choice(splits()["pose"][split]))
    rotations, mix = pose_rotations(pose, base.skeleton), {}
    if pose_variety > 0:
        rotations, mix = mixed_pose(rotations, split, base.skeleton, r_mix, pose_variety)
    rotations = skinning.perturb_rotations(rotations, base.skeleton.names, r_pose, strength=1.0 + pose_variety)
    return params, shaped, pose, rotations, mix


# The body's parts a mixed pose takes from other poses of the split, by bone name (the root, which
# lays a body down or stands it up, goes with the trunk)
LIMB_GROUPS = {
    "trunk": ("root", "spine", "neck", "head"),
    "arm.L": ("clavicle.L", "shoulder", "upperarm", "lowerarm", "wrist", "metacarpal", "finger"),
    "arm.R": ("clavicle.R", "shoulder", "upperarm", "lowerarm", "wrist", "metacarpal", "finger"),
    "leg.L": ("pelvis.L", "upperleg", "lowerleg", "foot", "toe"),
    "leg.R": ("pelvis.R", "upperleg", "lowerleg", "foot", "toe"),
}
# A left-right mirror in the mesh frame (x is the body's left-right axis)
MIRROR = np.diag([-1.0, 1.0, 1.0])


def limb_bones(group: str, names: tuple[str, ...]) -> np.ndarray:
    """Indices of the bones of a LIMB_GROUPS group."""
    side = group[-2:] if group != "trunk" else ""
    prefixes = LIMB_GROUPS[group]
    return np.array([k for k, name in enumerate(names) if name.startswith(prefixes) and name.endswith(side)
                     and (group != "trunk" or not name.endswith((".L", ".R")))], dtype=int)


def mirrored_pose(rotations: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """The pose's mirror image: each bone takes its other side's rotation, mirrored (the
    rotations are in the mesh frame, so the mirror is M R M)."""
    index = {name: k for k, name in enumerate(names)}
    other = [index.get(name[:-1] + {"L": "R", "R": "L"}[name[-1]], k) if name.endswith((".L", ".R")) else k
             for k, name in enumerate(names)]
    return MIRROR @ rotations[other] @ MIRROR


def mixed_pose(rotations: np.ndarray, split: str, skeleton, rng: np.random.Generator,
               variety: float) -> tuple[np.ndarray, dict]:
    """The catalogue pose's local rotations (B, 3, 3) with each limb group (LIMB_GROUPS) taken,
    with probability `variety`, from another pose of the same split (never another split's:
    the held-out poses stay held out), as it is or from that pose's mirror image. The legs hang
    from the root, whose rotation the catalogue's poses undo in the spine and the pelvis (a pose
    may turn its root half over), so a leg keeps its turn relative to the lowest spine bone of
    its own pose, not to the root. Returns the rotations and {group: "pose" or "pose
    (mirrored)"} for the groups replaced."""
    names, poses = skeleton.names, splits()["pose"][split]
    root, spine = names.index("root"), names.index("spine05")
    sources, mix = {}, {}
    for group in LIMB_GROUPS:
        if rng.random() >= variety:
            sources[group] = rotations
            continue
        donor, mirrored = str(rng.choice(poses)), bool(rng.random() < 0.5)
        source = pose_rotations(donor, skeleton)
        sources[group] = mirrored_pose(source, names) if mirrored else source
        mix[group] = donor + (" (mirrored)" if mirrored else "")
    out = rotations.copy()
    for group, source in sources.items():
        bones = limb_bones(group, names)
        out[bones] = source[bones]
    for side in "LR":
        source, pelvis = sources[f"leg.{side}"], names.index(f"pelvis.{side}")
        hips, source_hips = out[root] @ out[spine], source[root] @ source[spine]
        out[pelvis] = out[root].T @ hips @ source_hips.T @ source[root] @ source[pelvis]
    return out, mix


def _assemble(parts, posed, root, face_mask, metadata, joints) -> Person:
    texture, uvs = _atlas(parts)
    offsets = np.cumsum([0] + [len(v) for v in posed])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    vertices = np.concatenate(posed)
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    new_id = np.cumsum(used) - 1
    vertices = vertices[used]
    offset = np.array([root[0], vertices[:, 1].min(), root[2]])  # feet on y = 0, root above 0
    vertices -= offset
    faces = new_id[faces].astype(np.int32)
    face_uv = np.concatenate(uvs).astype(np.float32)
    face_ids = np.flatnonzero(used[:len(face_mask)] & face_mask)
    return Person(
        vertices=vertices.astype(np.float32), faces=faces, face_uv=face_uv, texture=texture,
        vertex_albedo=_vertex_albedo(texture, faces, face_uv, len(vertices)),
        face_part=np.concatenate([np.full(len(p.faces), p.part, np.uint8) for p in parts]),
        face_vertex_ids=new_id[face_ids].astype(np.int64), metadata=metadata,
        joints=(joints - offset).astype(np.float32))
