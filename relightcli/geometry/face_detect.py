"""The 128x128 face crop around a face box (pixels of the image): the square the face fit and
the face refinement net work in (relightcli.geometry.face.face_box_around places the box
around a face's landmarks)."""

from __future__ import annotations

from dataclasses import dataclass

FACE_CROP_SIZE = 128
FACE_CROP_MARGIN = 1.6


@dataclass(frozen=True)
class FaceBox:
    """A face in pixels of the image: the axis-aligned box (left, top, width, height)."""

    left: float
    top: float
    width: float
    height: float

    @property
    def centre(self) -> tuple[float, float]:
        return self.left + self.width / 2.0, self.top + self.height / 2.0


@dataclass(frozen=True)
class CropRect:
    """A square crop of the image: rows top .. top + size, columns left .. left + size
    (may reach outside the image: pad when cutting), sampled at `resolution` pixels."""

    left: int
    top: int
    size: int
    resolution: int = FACE_CROP_SIZE

    def world_rect(self, image_rect, image_shape) -> tuple:
        """(x0, x1, y0, y1) world rectangle of the crop, given the world rectangle of the
        whole (H, W) image (DESIGN.md: pixel edges at x0 + j (x1 - x0) / W)."""
        x0, x1, y0, y1 = (float(c) for c in image_rect)
        height, width = image_shape[:2]
        dx, dy = (x1 - x0) / width, (y1 - y0) / height
        return (x0 + self.left * dx, x0 + (self.left + self.size) * dx,
                y1 - (self.top + self.size) * dy, y1 - self.top * dy)


def face_crop_rect(box: FaceBox, *, margin: float = FACE_CROP_MARGIN,
                   resolution: int = FACE_CROP_SIZE) -> CropRect:
    """The square crop around a face box for the face refinement net: side = margin times
    the box's larger side, centred on the box (pixels of the image)."""
    side = max(1, int(round(margin * max(box.width, box.height))))
    cx, cy = box.centre
    return CropRect(left=int(round(cx - side / 2.0)), top=int(round(cy - side / 2.0)),
                    size=side, resolution=resolution)
