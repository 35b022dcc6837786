"""The faces: MediaPipe's face detector and face mesh on each person's head, the ICT FaceKit model
fitted to each, the fitted heads ray-traced under the target environment and the face refinement
net blended into the body's shading."""

from __future__ import annotations

import numpy as np

from relightcli.stages.frame import FoundFace, Frame, Models, PerceptionView, resample
from relightcli.stages.shading import sampling_effort


def person_mask_at(mask: np.ndarray, point) -> float:
    """The (R, R) mask's value at the nearest pixel to `point` (col, row) pixel indices; 0
    outside the crop."""
    col, row = (int(round(float(v))) for v in point)
    inside = 0 <= row < mask.shape[0] and 0 <= col < mask.shape[1]
    return float(mask[row, col]) if inside else 0.0


def stage_face(frame: Frame, options, models: Models) -> None:
    """Find every person's face and fit the ICT model to each (relightcli.geometry.face):
    MediaPipe's face detector on a head square placed by each found person's pose landmarks
    (the person crop's square when no person was found), the face mesh on the best detection,
    its 468 points -> the model's 68 landmarks (geometry.face_correspondence), the fit in a 128
    face crop framed around them. Planned only when a face refinement net ships to consume the
    fits (pipeline.plan_stages). The note lists each head: its face's box and scores, the fit's
    residual and crop, or why it has no fit; `skipped` when no face was fitted at all."""
    from relightcli.geometry.face import CropRect, fit_face_to_landmarks
    from relightcli.geometry.face_correspondence import load_correspondence
    from relightcli.nets.blaze import RotatedRect
    from relightcli.nets.face_mesh import find_face, head_rect

    frame.view = frame.view or PerceptionView.of(frame.image)
    srgb, scale = frame.view.image, np.asarray(frame.view.scale)
    box = frame.box
    heads = [(f"person {k}", head_rect(p.pose.landmarks)) for k, p in enumerate(frame.people)]
    if not heads:  # the person crop's square, in view pixels
        centre = (box.x0 + box.size / 2.0, box.y0 + box.size / 2.0) * scale
        heads = [("person crop (no person found)", RotatedRect(tuple(centre), box.size * scale[0], box.size * scale[1], 0.0))]
    frame.faces, report, fitted = [], [], []  # fitted: (head, landmarks' box) of each fit
    depth = None  # the person's front depth, made for the first face found
    for source, head in heads:
        entry = {"head": source}
        report.append(entry)
        face, why = find_face(srgb, head, models.get("face_detector"), models.get("face_mesh"))
        if face is None:
            entry["skipped"] = why
            continue
        entry.update(face.summary(tuple(scale)))
        # view pixels -> photo pixels (continuous) -> pixel indices of the person crop
        photo = load_correspondence().landmarks(face.mesh.points[:, :2]) / scale
        landmarks = (photo - (box.x0, box.y0)) / box.scale - 0.5
        centre = landmarks.mean(axis=0)
        if person_mask_at(frame.crop_mask, centre) < 0.5:
            entry["skipped"] = "the face found lies outside the person mask"
            continue
        same = [other for other, (lo, hi) in fitted if np.all(lo <= centre) and np.all(centre <= hi)]
        if same:  # two heads that overlap (people one behind the other) found the same face
            entry["skipped"] = f"the same face as {same[0]}'s"
            continue
        if depth is None:
            depth = np.where(frame.crop_mask > 0.5, frame.geometry.front_depth, np.nan)
        fit, info = fit_face_to_landmarks(landmarks, frame.crop.shape, depth=depth)
        entry.update(info)
        if fit is None:
            entry["skipped"] = info["skipped"].removesuffix(": face stage skipped")
            continue
        entry["path"] = "face mesh"
        fitted.append((source, (landmarks.min(axis=0), landmarks.max(axis=0))))
        frame.faces.append(FoundFace(source, fit, CropRect(*info["crop"])))
    frame.notes["face"] = {"path": "face mesh", "fitted": len(frame.faces), "faces": report}
    if not frame.faces:
        frame.notes["face"]["skipped"] = "no face: " + "; ".join(
            f"{entry['head']}: {entry['skipped']}" for entry in report) + ": face stage skipped"


def stage_face_refine(frame: Frame, options, models: Models) -> None:
    """The paper's face path, for each fitted face in turn: the fitted head ray-traced under
    the target environment in its 128x128 face crop, the face net on [that crop of the refined
    body shading, the coarse face shading], and the result blended into the body's shading over
    the face (the face pixels of the fitted model, feathered: geometry.face.face_blend_weight)
    in log shading, at most a factor of 2 from the body's (geometry.face.FACE_LOG_BOUND).
    Nothing changes when the face stage fitted no face."""
    if not frame.faces:
        frame.notes["face_refine"] = {"skipped": frame.notes.get("face", {}).get("skipped", "no face fit")}
        return
    frame.notes["face_refine"] = {"faces": [refine_face(frame, face, options, models) for face in frame.faces]}


def refine_face(frame: Frame, face: FoundFace, options, models: Models) -> dict:
    """One face of the face path (stage_face_refine) composited into frame.shading; what the
    report says of it."""
    from relightcli.geometry.face import FACE_LOG_BOUND, face_blend_weight, paste_crop

    patch, face_pixels, scale = face_shading(frame, face, options, models)
    frame.shading = paste_crop(frame.shading, patch, face_blend_weight(face_pixels), face.crop,
                               log_bound=FACE_LOG_BOUND)
    return {"head": face.head, "face_pixels": int(face_pixels.sum()), "scale": round(scale, 5)}


def render_faces_ahead(frame: Frame, options, models: Models) -> None:
    """Each fitted face's coarse render under frame.env, made before the face refinement asks
    for it: the pipeline's side line makes it after the fits while the calling thread refines
    the body (0.07 s a face off the calling thread at 512); the same rays, the same bytes."""
    for face in frame.faces:
        face.rendered = (frame.env, *render_face(frame, face, options, models))


def render_face(frame: Frame, face: FoundFace, options, models: Models):
    """(the fitted head's coarse shading (128, 128, 3) under frame.env, its face pixels (128,
    128) bool) in the face crop."""
    from relightcli.geometry.face import render_face_shading

    spp, target = sampling_effort(options)
    # Rendered at the face's own size in the person crop (e.g. 64 px at 512), then enlarged to
    # the net's 128 like the body crop: a quarter of the rays, and on the 89 validation
    # close-ups the net scores the same (19.64 vs 19.61 dB over the face)
    crop = face.crop
    coarse, face_pixels = render_face_shading(face.fit, models.light(frame.env),
                                              resolution=min(crop.size, crop.resolution), spp=spp,
                                              target_error=target, seed=options.seed, threads=1)
    return resample(coarse, crop.resolution), resample(face_pixels.astype(np.float32), crop.resolution) > 0.5


def rendered_face(frame: Frame, face: FoundFace, options, models: Models):
    """render_face's answer: the one made ahead when it was made under frame.env."""
    if face.rendered is not None and face.rendered[0] is frame.env:
        return face.rendered[1:]
    return render_face(frame, face, options, models)


def face_shading(frame: Frame, face: FoundFace, options, models: Models):
    """(the face net's shading (128, 128, 3) in the face crop, 0 outside the person; the fitted
    face's pixels (128, 128) bool; the crop's shading scale the net saw)."""
    from relightcli.geometry.face import cut_crop
    from relightcli.nets.refine import shading_scale

    crop = face.crop
    coarse, face_pixels = rendered_face(frame, face, options, models)
    # The net learned on crops normalised by their own scale (the person's pixels of the crop)
    # (times the soft crop mask, as the net learned it)
    mask = cut_crop(frame.crop_mask, crop)
    body = cut_crop(frame.shading, crop) * mask[..., None]
    scale = shading_scale(body, mask)
    refined = models.get("face_refine").predict(body, coarse, scale)
    # frame.shading is already the person's: only the patch is cut to the person's pixels, so
    # the rest of the body keeps its values exactly
    return np.maximum(refined, 0.0) * (mask[..., None] > 0), face_pixels, scale
