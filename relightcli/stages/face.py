"""The face: MediaPipe's face detector and face mesh on the person's head, the ICT FaceKit model
fitted to them, the fitted head ray-traced under the target environment and the face refinement
net blended into the body's shading."""

from __future__ import annotations

import numpy as np

from relightcli.stages.frame import Frame, Models, PerceptionView, resample
from relightcli.stages.shading import sampling_effort


def person_mask_at(mask: np.ndarray, point) -> float:
    """The (R, R) mask's value at the nearest pixel to `point` (col, row) pixel indices; 0
    outside the crop."""
    col, row = (int(round(float(v))) for v in point)
    inside = 0 <= row < mask.shape[0] and 0 <= col < mask.shape[1]
    return float(mask[row, col]) if inside else 0.0


def stage_face(frame: Frame, options, models: Models) -> None:
    """Find the face and fit the ICT model to it (relightcli.geometry.face): MediaPipe's face
    detector on a head square placed by each found person's pose landmarks in turn (the person
    crop's square when no person was found), the face mesh on the best detection, its 468
    points -> the model's 68 landmarks (geometry.face_correspondence), the fit in the 128 face
    crop framed around them. Planned only when a face refinement net ships to consume the fit
    (pipeline.plan_stages). The note says which head square gave the face, or why none did."""
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
    reasons = {}
    for source, head in heads:
        face, reasons[source] = find_face(srgb, head, models.get("face_detector"), models.get("face_mesh"))
        if face is None:
            continue
        # view pixels -> photo pixels (continuous) -> pixel indices of the person crop
        photo = load_correspondence().landmarks(face.mesh.points[:, :2]) / scale
        landmarks = (photo - (box.x0, box.y0)) / box.scale - 0.5
        if person_mask_at(frame.crop_mask, landmarks.mean(axis=0)) >= 0.5:
            break
        reasons[source] = "the face found lies outside the person mask"
    else:
        frame.notes["face"] = {"path": "face mesh", "skipped": "no face: " + "; ".join(
            f"{source}: {why}" for source, why in reasons.items()) + ": face stage skipped"}
        frame.face_fit, frame.face_crop = None, None
        return
    depth = np.where(frame.crop_mask > 0.5, frame.geometry.front_depth, np.nan)
    fit, info = fit_face_to_landmarks(landmarks, frame.crop.shape, depth=depth)
    frame.notes["face"] = {"path": "face mesh", "head": source, **face.summary(tuple(scale)), **info}
    frame.face_fit = fit
    frame.face_crop = CropRect(*info["crop"]) if fit is not None else None


def stage_face_refine(frame: Frame, options, models: Models) -> None:
    """The paper's face path: the fitted head ray-traced under the target environment in the
    128x128 face crop, the face net on [that crop of the refined body shading, the coarse face
    shading], and the result blended into the body's shading over the face (the face pixels
    of the fitted model, feathered: geometry.face.face_blend_weight). Nothing changes when the
    face stage found no face."""
    from relightcli.geometry.face import cut_crop, face_blend_weight, paste_crop, render_face_shading
    from relightcli.nets.refine import shading_scale

    if frame.face_fit is None:
        frame.notes["face_refine"] = {"skipped": frame.notes.get("face", {}).get("skipped", "no face fit")}
        return
    spp, target = sampling_effort(options)
    # Rendered at the face's own size in the person crop (e.g. 64 px at 512), then enlarged to
    # the net's 128 like the body crop: a quarter of the rays, and on the 89 validation
    # close-ups the net scores the same (19.64 vs 19.61 dB over the face)
    crop = frame.face_crop
    coarse, face_pixels = render_face_shading(frame.face_fit, models.light(frame.env),
                                              resolution=min(crop.size, crop.resolution), spp=spp,
                                              target_error=target, seed=options.seed, threads=1)
    coarse = resample(coarse, crop.resolution)
    face_pixels = resample(face_pixels.astype(np.float32), crop.resolution) > 0.5
    # The net learned on crops normalised by their own scale (the person's pixels of the crop)
    # (times the soft crop mask, as the net learned it)
    mask = cut_crop(frame.crop_mask, crop)
    body = cut_crop(frame.shading, crop) * mask[..., None]
    scale = shading_scale(body, mask)
    refined = models.get("face_refine").predict(body, coarse, scale)
    # frame.shading is already the person's: only the patch is cut to the person's pixels, so
    # the rest of the body keeps its values exactly
    patch = np.maximum(refined, 0.0) * (mask[..., None] > 0)
    frame.shading = paste_crop(frame.shading, patch, face_blend_weight(face_pixels), crop)
    frame.notes["face_refine"] = {"face_pixels": int(face_pixels.sum()), "scale": round(scale, 5)}
