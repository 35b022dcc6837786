"""Time per body fit and joint-position error on synthetic people: T-pose, A-pose, arms up
and crossed arms posed on the shipped body model with a random shape, turned, placed in a
512 px crop, observed as BlazePose would report them (observe_landmarks) plus noise
(1.5 px, 2 cm), then fitted by relightcli.geometry.body_fit.fit_body.

    python bench/bench_body_fit.py [--repeats 3] [--threads 2]

Prints, per pose and silhouette (none; the mask rasterised from the true body; that mask
dilated by 10 px, as clothes would make it): the mean and worst error of the 12 main joints
(cm, metric body space, hip-centred), their mean error in the image plane (x, y), the same
3D error for the closed-form initialisation, the keypoint RMS (px), the IoU of the fitted
body's silhouette with the true mask and the median time per fit (ms).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

# Directions (model frame: +X the person's left, +Y up, +Z towards the camera) per pose
POSES = {
    "T-pose": {"upperarm01.L": (1, 0, 0), "upperarm01.R": (-1, 0, 0),
               "lowerarm01.L": (1, 0, 0), "lowerarm01.R": (-1, 0, 0)},
    "A-pose": {"upperarm01.L": (0.7, -0.7, 0), "upperarm01.R": (-0.7, -0.7, 0),
               "lowerarm01.L": (0.6, -0.8, 0.1), "lowerarm01.R": (-0.6, -0.8, 0.1)},
    "arms-up": {"upperarm01.L": (0.2, 1, 0), "upperarm01.R": (-0.2, 1, 0),
                "lowerarm01.L": (0.1, 1, 0.1), "lowerarm01.R": (-0.1, 1, 0.1)},
    "crossed-arms": {"upperarm01.L": (0.15, -0.7, 0.45), "upperarm01.R": (-0.15, -0.7, 0.45),
                     "lowerarm01.L": (-1, 0.15, 0.25), "lowerarm01.R": (1, 0.2, 0.35)},
}
LEGS = {"upperleg01.L": (0.15, -1, 0.05), "upperleg01.R": (-0.12, -1, 0.0),
        "lowerleg01.L": (0.1, -1, -0.1), "lowerleg01.R": (-0.05, -1, -0.05)}


def synthetic_person(model, pose: str, rng: np.random.Generator, resolution: int = 512,
                     noise_px: float = 1.5, noise_m: float = 0.02):
    """Truth (shape, rotations, translation, scale) and BlazePose-like observations
    (keypoints (33, 2) px, visibility (33,), world (33, 3) m) of one synthetic person."""
    from relightcli.geometry import body_fit

    shape = np.clip(rng.normal(0.0, 0.7, model.n_shape), -2, 2)
    rotations = model.rest_pose()
    names = model.joint_names
    # A turned root and a slightly bent spine and neck, which the initialisation ignores
    rotations[0] = body_fit.axis_angle_to_matrix(np.array([0.0, rng.uniform(-0.5, 0.5), 0.0]))
    for bone in ("spine04", "spine02", "neck01"):
        rotations[names.index(bone)] = body_fit.axis_angle_to_matrix(rng.normal(0, 0.08, 3))
    rotations = body_fit.aim_limbs(model, rotations, {**POSES[pose], **LEGS}, shape)
    scale = rng.uniform(0.9, 1.05)
    translation = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.0])
    pixels, world = body_fit.observe_landmarks(model, shape, rotations, translation, scale,
                                               resolution)
    keypoints = pixels + rng.normal(0, noise_px, pixels.shape)
    world = world + rng.normal(0, noise_m, world.shape)
    return (shape, rotations, translation, scale), (keypoints, np.ones(33), world)


def joint_errors_cm(model, truth, shape, rotations) -> np.ndarray:
    """(12,) cm: hip-centred metric distance of the main joints, fitted vs true."""
    return 100 * np.linalg.norm(joint_offsets(model, truth, shape, rotations), axis=1)


def joint_offsets(model, truth, shape, rotations) -> np.ndarray:
    """(12, 3) m: hip-centred main joints, fitted minus true (x, y in the image plane)."""
    from relightcli.geometry.body_fit import CORE_LANDMARKS

    def core(s, r):
        _, _, landmarks = model.posed(s, r)
        landmarks = landmarks - landmarks[[23, 24]].mean(axis=0)
        return landmarks[list(CORE_LANDMARKS)]

    return core(shape, rotations) - core(truth[0], truth[1])


def silhouettes(model, truth, resolution: int = 512) -> dict:
    """name -> (R, R) float32 mask or None: none, the true body's, and it dilated by 10 px."""
    import cv2

    from relightcli.geometry.body_fit import body_silhouette

    vertices, _, _ = model.posed(*truth)
    mask = body_silhouette(model, vertices, resolution).astype(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21))
    return {"none": None, "mask": mask.astype(np.float32),
            "dilated": cv2.dilate(mask, disc).astype(np.float32)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, str(args.threads))
    from relightcli.geometry.body_fit import body_silhouette, fit_body, initial_pose
    from relightcli.geometry.body_model import BodyModel

    model = BodyModel.load()
    print(f"{'pose':14s} {'mask':8s} {'joint cm':>9s} {'worst':>6s} {'2D cm':>6s} "
          f"{'init cm':>8s} {'px':>5s} {'IoU':>5s} {'ms':>6s}")
    for pose in POSES:
        rng = np.random.default_rng(7)
        rows = {}
        for _ in range(args.repeats):
            truth, (keypoints, visibility, world) = synthetic_person(model, pose, rng)
            masks = silhouettes(model, truth)
            init = joint_errors_cm(model, truth, None, initial_pose(model, world))
            for name, silhouette in masks.items():
                start = time.perf_counter()
                fit = fit_body(model, keypoints, visibility, world, silhouette, resolution=512)
                elapsed = time.perf_counter() - start
                offsets = 100 * joint_offsets(model, truth, fit.shape, fit.rotations)
                errors = np.linalg.norm(offsets, axis=1)
                body = body_silhouette(model, fit.vertices, 512)
                true = masks["mask"] > 0
                iou = (body & true).sum() / (body | true).sum()
                rows.setdefault(name, []).append((
                    errors.mean(), errors.max(), np.linalg.norm(offsets[:, :2], axis=1).mean(),
                    init.mean(), fit.residual_px, iou, elapsed))
        for name, values in rows.items():
            mean, worst, plane, init, px, iou, _ = np.mean(values, axis=0)
            ms = 1000 * np.median([r[-1] for r in values])
            print(f"{pose:14s} {name:8s} {mean:9.2f} {worst:6.2f} {plane:6.2f} {init:8.2f} "
                  f"{px:5.2f} {iou:5.3f} {ms:6.0f}")


if __name__ == "__main__":
    main()
