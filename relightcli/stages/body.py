"""The body: a MakeHuman body fitted under each person found, and the fitted bodies' prior maps
(depth and normals) in the crop."""

from __future__ import annotations

import cv2
import numpy as np

from relightcli import compose
from relightcli.geometry.body_fit import depth_side
from relightcli.nets.lift import image_depths
from relightcli.stages.crop import person_keypoints_in_crop
from relightcli.stages.frame import Frame, Models


def stage_body(frame: Frame, options, models: Models) -> None:
    """The body model fitted to each person found (relightcli.geometry.body_fit): their 33
    keypoints in the crop, BlazePose's visibility and world landmarks, the crop mask as the
    silhouette. frame.bodies keeps the fits (vertices in the crop's world frame);
    frame.notes["body"] per person the seconds, RMS keypoint residual (crop pixels), whether
    the fit converged (or why not) and, if it did, whether the fitted body faces the camera
    (`seen_from` front or behind: BlazePose takes some front-facing people for back views and
    the other way round: docs/RESULTS.md, The body and the face), and `turn` when the fit was
    redone to the mirrored turn the image landmarks' depths ask for (body_fit.depth_side)."""
    import time

    model = models.body_model()
    lifter = models.get("lift") if models.has("lift") else None
    silhouette = (frame.crop_mask > 0.5).astype(np.float32)
    fits, people = [], []
    for person in frame.people:
        start = time.perf_counter()
        landmarks, world = person.pose.landmarks, person.pose.world
        if lifter is not None:  # BlazePose's depths corrected (relightcli.nets.lift)
            world = lifter.lift(landmarks, world)
            landmarks = image_depths(landmarks, world)
        fit = _fit_on_one_opencv_thread(model, person_keypoints_in_crop(person, frame.view.scale, frame.box),
                                        landmarks[:, 3], world, silhouette, models, depth_side(landmarks))
        fits.append(fit)
        residual = float(fit.residual_px)
        note = {"seconds": round(time.perf_counter() - start, 4),
                "residual_px": round(residual, 3) if np.isfinite(residual) else None,
                "converged": bool(fit.converged), "reason": fit.reason}
        if fit.converged:
            note["seen_from"] = "front" if fit.faces_camera else "behind"
            if fit.turn_mirrored:
                note["turn"] = "mirrored: the landmarks' depths say the other way"
        people.append(note)
    frame.bodies = fits
    frame.notes["body"] = {"people": people}


def _fit_on_one_opencv_thread(model, keypoints, visibility, world, silhouette, models=None, turn_witness=None):
    """fit_body with OpenCV and BLAS on one thread and without Intel IPP: the silhouette term's
    OpenCV calls round differently with another thread count (1e-8 on the vertices), and with
    IPP its precise distance transform differed from one process to the next on the same input
    (two or three outcomes in six runs, 1e-8 on the fit's residual, a half-float step in a few
    shading pixels); numpy's BLAS keeps its default threads in a process that loaded numpy
    before relightcli, and two people's fits rounded differently then (one code value in a few
    head pixels). An item's outputs must not depend on any of them (tests/test_determinism.py),
    whichever entry point runs the stage (the pipeline, the data factory's coarse maps).
    `models`: whose prefetch thread the BLAS limit's library scan waits for (one_blas_thread)."""
    from relightcli.geometry.body_fit import fit_body
    from relightcli.stages.frame import one_blas_thread

    threads, ipp = cv2.getNumThreads(), cv2.ipp.useIPP()
    cv2.setNumThreads(1)
    cv2.ipp.setUseIPP(False)
    try:
        with one_blas_thread(models):
            return fit_body(model, keypoints, visibility, world, silhouette, turn_witness=turn_witness)
    finally:
        cv2.setNumThreads(threads)
        cv2.ipp.setUseIPP(ipp)


def stage_body_maps(frame: Frame, options, models: Models) -> None:
    """The prior maps of every converged body fit (relightcli.geometry.body_maps): front and
    back depth and normals at the person's pixels (crop mask > 0), traced once per photo in the
    Embree scene of those bodies (kept for the ray tracer, closed by the pipeline); body_hits:
    the front hits, which the ray tracer shades with the body's own normals. Nothing when no
    fit converged (the note says why). The person's pixels only: at 512 on the skier example the
    maps take 0.053 s of CPU (0.076 over the whole crop under the bodies' bounds; the ray
    tracer's own front trace of the bodies, which they replace, took 0.038)."""
    from relightcli.geometry.body_maps import bodies_scene, render_body_maps

    fitted = [fit.vertices for fit in frame.bodies if fit.converged]
    if not fitted:
        frame.notes["body_maps"] = {"skipped": "no converged body fit"}
        return
    frame.body_scene = bodies_scene(fitted, models.body_model().triangles)
    frame.body_maps = render_body_maps(frame.body_scene, options.resolution, where=frame.crop_mask > 0)
    frame.body_hits = frame.body_maps.front
    person = frame.crop_mask > 0.5
    frame.notes["body_maps"] = {"bodies": len(fitted),
                                "person_pixels_covered": round(float(frame.body_maps.mask[person].mean()), 4)
                                if person.any() else 0.0}


def body_shading_pixels(frame: Frame) -> np.ndarray:
    """(R, R) bool: the crop pixels where the fitted bodies' shading is used: all but those of
    a person whose fit did not converge (their pose segmentation), who keep the reconstruction's."""
    usable = np.ones(frame.crop_mask.shape, bool)
    height, width = frame.image.shape[:2]
    for person, fit in zip(frame.people, frame.bodies):
        if not fit.converged:
            mask = frame.view.to_photo_size(person.pose.mask, height, width)
            usable &= compose.crop_square(mask, frame.box) <= 0.5
    return usable
