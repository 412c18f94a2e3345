"""The camera's starting pose from detected landmarks: PnP of the shape model's landmark vertices
against the photo's 468 FaceMesh points."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from ..render.camera import Camera

__all__ = ["initial_camera"]


def initial_camera(landmarks_px: np.ndarray, model_points: np.ndarray, width: int, height: int, focal_px: float,
                   weights: np.ndarray | None = None, principal: np.ndarray | None = None) -> Camera:
    """landmarks_px: (N, 2) detected points in pixels; model_points: (N, 3) the same points on the shape
    model (mm, world frame); weights: (N,) > 0 selects the points used (None: all). Returns a batch-1
    Camera (principal point at the image centre) whose projection of ``model_points`` best matches
    the landmarks (SQPnP, then Levenberg-Marquardt refinement). ``principal``: (2,) pixels, default the
    image centre (a crop's principal point is the full photo's centre, mapped into the crop)."""
    pts2 = np.asarray(landmarks_px, np.float64)
    pts3 = np.asarray(model_points, np.float64)
    if pts2.ndim != 2 or pts2.shape[1] != 2 or pts3.shape != (len(pts2), 3):
        raise ValueError(f"expected (N, 2) landmarks and (N, 3) model points, got {pts2.shape} and {pts3.shape}")
    if weights is not None:
        keep = np.asarray(weights) > 0
        pts2, pts3 = pts2[keep], pts3[keep]
    if len(pts2) < 6:
        raise ValueError(f"need at least 6 landmarks for the pose, got {len(pts2)}")
    cx, cy = (width / 2, height / 2) if principal is None else (float(principal[0]), float(principal[1]))
    k = np.array([[focal_px, 0, cx], [0, focal_px, cy], [0, 0, 1]], np.float64)
    try:
        ok, rvec, tvec = cv2.solvePnP(pts3, pts2, k, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:  # SQPnP asserts when the face spans < ~1 degree (telephoto): nearly orthographic
        ok = False
    if not ok or tvec[2, 0] <= 0:
        rvec, tvec = _weak_perspective_start(pts2, pts3, focal_px, cx, cy)
        ok, rvec, tvec = cv2.solvePnP(pts3, pts2, k, None, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise ValueError("PnP failed for these landmarks")
    rvec, tvec = cv2.solvePnPRefineLM(pts3, pts2, k, None, rvec, tvec)
    rot, _ = cv2.Rodrigues(rvec)
    if tvec[2, 0] <= 0:  # a mirror solution behind the camera: never a real face
        raise ValueError("PnP put the face behind the camera")
    t = torch.tensor
    return Camera(t([[focal_px, focal_px]]), t([[cx, cy]]), t(rot[None], dtype=torch.float32),
                  t(tvec.reshape(1, 3), dtype=torch.float32), width, height)


def _weak_perspective_start(pts2: np.ndarray, pts3: np.ndarray, focal_px: float, cx: float, cy: float):
    """A frontal pose at the distance where the model's landmarks are as wide as the detected ones:
    a start for iterative PnP where SQPnP cannot work."""
    rot = np.diag([1.0, -1.0, -1.0])  # render.camera.frontal_rotation: the face toward the camera
    rvec, _ = cv2.Rodrigues(rot)
    spread3 = np.ptp(pts3[:, :2], axis=0).max()
    spread2 = max(np.ptp(pts2, axis=0).max(), 1e-6)
    z = focal_px * spread3 / spread2
    c3 = rot @ pts3.mean(0)
    c2 = pts2.mean(0)
    tvec = np.array([(c2[0] - cx) * (z + c3[2]) / focal_px - c3[0], (c2[1] - cy) * (z + c3[2]) / focal_px - c3[1], z])
    return rvec, tvec.reshape(3, 1)
