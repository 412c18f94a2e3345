"""Head pose (yaw, pitch, roll) from FaceMesh's 3D landmarks.

FaceMesh's x, y, z (image px, z away from the camera) are close to an orthographic view of the face.
We build the face frame from symmetric landmark pairs (its x axis) and the midline (its y axis), and
read the angles off it. No template fit, so it works for any face shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HeadPose", "head_pose", "face_rotation"]

# Symmetric pairs (image-left, image-right for a frontal face): eye corners, brows, cheeks, mouth corners.
_PAIRS = np.array([(33, 263), (133, 362), (70, 300), (105, 334), (234, 454), (127, 356), (61, 291), (58, 288)])
# The face's vertical: outer eye corners' midpoint to mouth corners' midpoint. These four points are
# nearly coplanar, so pitch 0 means that plane faces the camera. (Nasion-to-chin tilts ~10 degrees more:
# the chin sits back in FaceMesh depth.)
_TOP, _BOTTOM = (33, 263), (61, 291)


@dataclass(frozen=True)
class HeadPose:
    """Degrees. yaw > 0: the face turns toward the image's right; pitch > 0: the chin rises;
    roll > 0: the face tilts clockwise on screen."""

    yaw: float
    pitch: float
    roll: float


def face_rotation(points: np.ndarray) -> np.ndarray:
    """(468, 3) landmarks -> (3, 3) rotation whose columns are the face's x, y, z axes in camera
    coordinates (x right, y down, z away). A frontal, upright face gives the identity."""
    p = np.asarray(points, np.float64)
    if p.shape != (468, 3):
        raise ValueError(f"expected (468, 3) landmarks, got {p.shape}")
    x = (p[_PAIRS[:, 1]] - p[_PAIRS[:, 0]]).sum(0)
    x /= np.linalg.norm(x) + 1e-12
    y = p[list(_BOTTOM)].mean(0) - p[list(_TOP)].mean(0)
    y -= x * (x @ y)
    y /= np.linalg.norm(y) + 1e-12
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=1)


def head_pose(points: np.ndarray) -> HeadPose:
    """Intrinsic angles, R = Rz(roll) Ry(-yaw) Rx(-pitch): roll is the in-plane part, so rotating the
    photo changes only roll."""
    r = face_rotation(points)
    yaw = np.degrees(np.arctan2(r[2, 0], np.hypot(r[2, 1], r[2, 2])))
    pitch = -np.degrees(np.arctan2(r[2, 1], r[2, 2]))
    roll = np.degrees(np.arctan2(r[1, 0], r[0, 0]))
    return HeadPose(float(yaw), float(pitch), float(roll))
