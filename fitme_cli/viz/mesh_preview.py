"""A quick look at a mesh: orthographic, painter's algorithm, Lambert shading. For docs and sanity
pictures only; the differentiable renderer lives elsewhere."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["preview_mesh", "rotation_y"]


def rotation_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def preview_mesh(vertices: np.ndarray, triangles: np.ndarray, yaw_deg: float = 0.0, size: int = 320,
                 colour: tuple[int, int, int] = (200, 170, 150), extent: float | None = None,
                 centre: np.ndarray | None = None) -> np.ndarray:
    """(size, size, 3) uint8 RGB view of vertices (V, 3) (model axes: y up, z toward the viewer),
    turned by yaw about the vertical axis. ``extent`` (model units across the picture) and ``centre``
    fix the framing, so that several views compare."""
    v = np.asarray(vertices, np.float64)
    c = v.mean(0) if centre is None else centre
    p = (v - c) @ rotation_y(yaw_deg).T
    ext = extent or 1.1 * max(np.ptp(p[:, 0]), np.ptp(p[:, 1]))
    xy = np.stack([p[:, 0], -p[:, 1]], 1) / ext * size + size / 2
    t = triangles
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    light = np.array([0.3, 0.4, 1.0]) / np.linalg.norm([0.3, 0.4, 1.0])
    shade = 0.25 + 0.75 * np.clip(n @ light, 0, 1)
    front = n[:, 2] > 0
    order = np.argsort(p[t, 2].mean(1))
    img = np.full((size, size, 3), 255, np.uint8)
    base = np.asarray(colour, np.float64)
    for f in order:
        if not front[f]:
            continue
        pts = np.round(xy[t[f]] * 16).astype(np.int32)
        cv2.fillConvexPoly(img, pts, tuple(int(x) for x in base * shade[f]), cv2.LINE_AA, 4)
    return img
