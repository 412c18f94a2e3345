"""FaceMesh geometry: rotated square regions of interest, crop transforms, and landmark decoding.

A region of interest (ROI) is a rotated square in image pixels. FaceMesh sees it as an upright
192x192 crop in [0, 1] RGB and returns 468 (x, y, z) in crop pixels, z being depth relative to the
face centre in the same pixel scale as x (smaller z is nearer the camera). We map x, y back to image
pixels and scale z alike, so all three share image-pixel units.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "FACEMESH_SIZE",
    "Roi",
    "roi_from_detection",
    "roi_from_landmarks",
    "crop_affine",
    "crop",
    "warp_region",
    "landmarks_to_image",
    "IBUG68_FROM_FACEMESH",
]

FACEMESH_SIZE = 192
_ROI_SCALE = 1.5  # MediaPipe's face-landmark ROI: 1.5x the detection/landmark box, square on the long side

# FaceMesh vertex for each iBUG-68 point, in iBUG order: jaw 0-16 (image-left to image-right for a
# frontal face), brows 17-26, nose 27-35, eyes 36-47, outer lips 48-59, inner lips 60-67. Checked
# against dlib's 68-point shape predictor in tests/test_facemesh.py.
IBUG68_FROM_FACEMESH = np.array([
    127, 234, 132, 58, 172, 136, 149, 148, 152, 377, 378, 365, 397, 288, 361, 454, 356,
    70, 63, 105, 66, 107, 336, 296, 334, 293, 300,
    168, 197, 5, 4, 75, 97, 2, 326, 305,
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181,
    78, 82, 13, 312, 308, 317, 14, 87,
], dtype=np.int64)


@dataclass(frozen=True)
class Roi:
    """A rotated square: centre (x, y) and side in image pixels; angle in radians, the face's in-plane
    rotation (positive = clockwise on screen, since y points down)."""

    cx: float
    cy: float
    size: float
    angle: float


def _roi(cx: float, cy: float, w: float, h: float, angle: float) -> Roi:
    return Roi(float(cx), float(cy), float(max(w, h) * _ROI_SCALE), float(angle))


def roi_from_detection(box: np.ndarray, keypoints: np.ndarray) -> Roi:
    """ROI from a BlazeFace box (x0, y0, x1, y1) and keypoints (6, 2), both in image pixels.

    The angle comes from the line between the eyes, keypoints 0 and 1.
    """
    d = keypoints[1] - keypoints[0]
    angle = np.arctan2(d[1], d[0])
    return _roi((box[0] + box[2]) / 2, (box[1] + box[3]) / 2, box[2] - box[0], box[3] - box[1], angle)


def roi_from_landmarks(points: np.ndarray) -> Roi:
    """ROI for the next FaceMesh pass from its own 468 landmarks (image px): MediaPipe's tracking rule.

    The box is taken in the face's own rotated frame, angle from the outer eye corners 33 and 263.
    """
    xy = points[:, :2]
    d = xy[263] - xy[33]
    angle = float(np.arctan2(d[1], d[0]))
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, s], [-s, c]])  # image -> face frame
    local = xy @ rot.T
    lo, hi = local.min(0), local.max(0)
    centre = ((lo + hi) / 2) @ rot  # back to image
    w, h = hi - lo
    return _roi(centre[0], centre[1], w, h, angle)


def crop_affine(roi: Roi, out_size: int = FACEMESH_SIZE) -> np.ndarray:
    """2x3 affine mapping image pixels to crop pixels (the ROI upright, filling out_size x out_size)."""
    k = out_size / roi.size
    c, s = np.cos(roi.angle), np.sin(roi.angle)
    a = np.array([[c, s], [-s, c]]) * k
    t = np.array([out_size / 2, out_size / 2]) - a @ np.array([roi.cx, roi.cy])
    return np.concatenate([a, t[:, None]], axis=1).astype(np.float64)


def crop(image: np.ndarray, roi: Roi, out_size: int = FACEMESH_SIZE) -> np.ndarray:
    """The ROI of ``image`` (H, W, 3) uint8 as an upright (out_size, out_size, 3) uint8 crop.

    Outside the image is black, as in MediaPipe. A ROI much larger than the crop is first cut out and
    area-downscaled, so the bilinear warp neither aliases nor touches the rest of a 12 MP photo.
    """
    return warp_region(image, crop_affine(roi, out_size), roi.cx, roi.cy, roi.size, out_size)


def warp_region(image: np.ndarray, m: np.ndarray, cx: float, cy: float, size: float, out_size: int) -> np.ndarray:
    """cv2.warpAffine of ``image`` by ``m`` (image px -> out px) into out_size², anti-aliased.

    (cx, cy, size) bound the source region (a square of side ``size``, any rotation).
    """
    scale = size / out_size
    if scale <= 2.0:
        return cv2.warpAffine(image, m, (out_size, out_size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    half = size * 0.75  # > size/sqrt(2): covers the square at any rotation
    h, w = image.shape[:2]
    x0, y0 = max(int(cx - half), 0), max(int(cy - half), 0)
    x1, y1 = min(int(np.ceil(cx + half)), w), min(int(np.ceil(cy + half)), h)
    if x1 <= x0 or y1 <= y0:
        return np.zeros((out_size, out_size, image.shape[2]), image.dtype)
    sub = image[y0:y1, x0:x1]
    f = 2.0 / scale
    nw, nh = max(int(round(sub.shape[1] * f)), 1), max(int(round(sub.shape[0] * f)), 1)
    sub = cv2.resize(sub, (nw, nh), interpolation=cv2.INTER_AREA)
    fx, fy = nw / (x1 - x0), nh / (y1 - y0)
    # pixel centres: image_px = (sub_px + 0.5) / f - 0.5 + offset
    to_image = np.array([[1 / fx, 0, x0 + 0.5 / fx - 0.5], [0, 1 / fy, y0 + 0.5 / fy - 0.5], [0, 0, 1]])
    m2 = (np.vstack([m, [0, 0, 1]]) @ to_image)[:2]
    return cv2.warpAffine(sub, m2, (out_size, out_size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def landmarks_to_image(raw: np.ndarray, roi: Roi, out_size: int = FACEMESH_SIZE) -> np.ndarray:
    """raw (1404,) or (468, 3) FaceMesh output in crop pixels -> (468, 3) float32 in image pixels."""
    pts = np.asarray(raw, np.float64).reshape(468, 3)
    m = crop_affine(roi, out_size)
    inv = cv2.invertAffineTransform(m)
    xy = pts[:, :2] @ inv[:, :2].T + inv[:, 2]
    z = pts[:, 2] * (roi.size / out_size)
    return np.concatenate([xy, z[:, None]], axis=1).astype(np.float32)
