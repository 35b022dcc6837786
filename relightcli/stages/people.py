"""The people and the person mask: everyone in the photo found by MediaPipe's BlazePose (or a
portrait's face), and the mask from their segmentations when the input brought none."""

from __future__ import annotations

import cv2
import numpy as np

from relightcli import compose
from relightcli.errors import RelightError
from relightcli.stages.frame import Frame, Models, PerceptionView


def stage_people(frame: Frame, options, models: Models) -> None:
    """Every person in the photo: BlazePose's person detector, then per person the landmark net
    (33 keypoints, 33 metric world landmarks, a segmentation) in a crop turned upright
    (relightcli.nets.pose), on the photo as sRGB. When the detector finds nobody and the input
    brings a mask, the landmark net looks in the mask's box (find_person_in_mask: BlazePose's
    detector misses some people its landmark net sees, e.g. T-posed synthetic figures, or a
    visor that hides the face). Without a mask it looks at the whole photo instead
    (find_person_in_photo): the detector missed the T-posed figures of 25 of the 170 synthetic
    validation photos (data/evalval512, data/evalval256), 22 are found so (the net's mask
    against the true one: IoU 0.67-0.95, mean 0.87), and so is Aldrin behind his gold visor.
    When no body is found but the face detector and face mesh find a face in the whole photo (a
    close portrait: head and shoulders), the selfie segmentation gives that person's mask. The
    report lists who was found, who the landmark net turned down, and the fallbacks that ran."""
    from relightcli.nets.face_mesh import find_face
    from relightcli.nets.pose import WHOLE_PHOTO_PRESENCE, find_people, find_person_in_mask, find_person_in_photo

    frame.view = frame.view or PerceptionView.of(frame.image)
    srgb, scale = frame.view.image, frame.view.scale
    people = find_people(srgb, models.get("person_detector"), models.get("pose_landmarks"),
                         join_views=frame.mask is None)  # an input mask: no use for more views
    frame.people = [p for p in people if p.found]
    frame.notes["people"] = {"found": [p.summary(scale) for p in frame.people],
                             "turned_down": [p.summary(scale) for p in people if not p.found]}
    if frame.people:
        return
    if frame.mask is not None:  # the mask says where the person is: the landmark net there
        height, width = srgb.shape[:2]
        mask = cv2.resize(frame.mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        person = find_person_in_mask(srgb, mask, models.get("pose_landmarks"))
        if person is not None and person.found:
            frame.people = [person]
            frame.notes["people"]["found"] = [person.summary(scale)]
            frame.notes["people"]["from_mask"] = "no person detected: landmarks in the mask's box"
        else:  # the portrait's selfie mask would only stand in for the input's
            frame.notes["people"]["portrait"] = "no body found; the input brings the mask"
        return
    person = find_person_in_photo(srgb, models.get("pose_landmarks"))
    if person.pose.presence >= WHOLE_PHOTO_PRESENCE:
        frame.people = [person]
        frame.notes["people"]["found"] = [person.summary(scale)]
        frame.notes["people"]["whole_photo"] = "no person detected: landmarks in the whole photo"
        return
    frame.notes["people"]["whole_photo"] = f"no person detected; presence {person.pose.presence:.3f} in the whole photo"
    face, why = find_face(srgb, None, models.get("face_detector"), models.get("face_mesh"))
    if face is None:
        frame.notes["people"]["portrait"] = f"no body and no face: {why}"
        return
    frame.portrait_mask = models.get("selfie_segmentation").segment(srgb)
    frame.notes["people"]["portrait"] = {"face": face.summary(scale), "mask": "selfie segmentation"}


MASK_FLOOR = 0.5 / 255  # a predicted mask below this is 0 (stage_mask)


def stage_mask(frame: Frame, options, models: Models) -> None:
    """The person mask when the input brought none: the union of the people's segmentations
    (soft, the hair's edge included; each the landmark net's over its views of the person: the
    crop, its mirror image, the other refinement pass's crop; relightcli.nets.pose.find_people),
    or a portrait's selfie segmentation, its edges pulled to the photo's by a guided filter in
    the crop around everyone (compose.snap_mask). No person: the item fails, nothing is written.

    Measured (python bench/mask_iou.py, mean / worst IoU with the true mask): on the 17 of 20
    validation scenes where a person is found, 0.938 / 0.826 raw, 0.942 / 0.830 with the
    filter (radius 2 px at 512, eps 0.01: chosen there among radii 2-16 and eps 1e-4..1e-2;
    GrabCut in a 3-7 px band scored about the same at +170 ms, with a hard edge); on the 20 test
    scenes 0.962 / 0.926, where the synthetic-trained mask net + GrabCut it replaces scored
    0.903 / 0.758 (COCO skier 0.918 against 0.798)."""
    if frame.mask is not None:
        return
    if frame.people:
        union = np.max([p.pose.mask for p in frame.people], axis=0)
        count = len(frame.people)
        source = f"pose segmentation of {count} {'person' if count == 1 else 'people'}"
    elif frame.portrait_mask is not None and (frame.portrait_mask > 0.5).any():
        union, source = frame.portrait_mask, "selfie segmentation (a face, no body found)"
    else:
        raise RelightError("no person found in the photo",
                           fix="pass --mask FILE to say where the person is (white: person)")
    frame.mask = frame.view.to_photo_size(union, *frame.image.shape[:2]).copy()
    box = compose.person_crop_box(frame.mask, options.resolution)
    snapped = compose.snap_mask(compose.crop_square(frame.image, box), compose.crop_square(frame.mask, box))
    compose.replace_in_box(frame.mask, snapped, box)
    # A segmentation is a probability, never quite 0: its faint tail covered 94% of the
    # example's crop, and every layer was made there, out of sight. What an 8-bit mask file
    # would store as 0 is 0
    frame.mask = np.where(frame.mask >= MASK_FLOOR, np.minimum(frame.mask, 1.0), 0.0).astype(np.float32)
    frame.mask_predicted = True
    frame.notes["mask"] = {"source": source, "edges": "guided filter"}
