"""The face stage (issue 6): detect the face, fit the ICT FaceKit model to its landmarks, and
give the fitted mesh in the crop's camera frame for the coarse face shading.

One import point for the pipeline; the parts live in
- face_model.py: the shipped linear model (models/face_model.npz) and the weak-perspective
  camera helpers (DESIGN.md pixel convention);
- face_fit.py: regularised Gauss-Newton fit of identity, expression and pose to 68 landmarks
  (optional weights, robust loss, optional depth), and the fitted mesh;
- face_detect.py: OpenCV cascade detection with a (None, reason) skip path, and the 128x128
  face crop rectangle.
"""

from relightcli.geometry.face_detect import CropRect, FaceBox, detect_face, face_crop_rect
from relightcli.geometry.face_fit import FaceFit, face_mesh, fit_face
from relightcli.geometry.face_model import (
    FaceModel,
    pixel_to_world,
    rotation_matrix,
    transform,
    world_to_pixel,
)

__all__ = ["CropRect", "FaceBox", "FaceFit", "FaceModel", "detect_face", "face_crop_rect",
           "face_mesh", "fit_face", "pixel_to_world", "rotation_matrix", "transform",
           "world_to_pixel"]
