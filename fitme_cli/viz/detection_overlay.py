"""Draw a detection for a person to check: the whole photo with every face box and score, beside a
zoomed panel of the chosen face with its mesh, iBUG-68 contours and head pose."""

from __future__ import annotations

import cv2
import numpy as np

from ..perception.detect import Detection, Face, FaceLandmarks

__all__ = ["draw_detection"]

# iBUG-68 polylines: jaw, brows, nose bridge, nostrils, eyes (closed), lips (closed)
_IBUG_LINES = [
    (range(0, 17), False), (range(17, 22), False), (range(22, 27), False), (range(27, 31), False),
    (range(31, 36), False), (range(36, 42), True), (range(42, 48), True), (range(48, 60), True), (range(60, 68), True),
]
_SHIFT = 4  # fixed-point bits for sub-pixel drawing
_CHOSEN, _OTHER, _MESH, _CONTOUR = (255, 220, 0), (0, 200, 255), (60, 230, 60), (255, 60, 60)


def _mesh_edges(xy: np.ndarray) -> np.ndarray:
    """Edges (E, 2, 2) of the Delaunay triangulation of the landmarks: a drawable mesh."""
    lo, hi = xy.min(0) - 1, xy.max(0) + 1
    sub = cv2.Subdiv2D((int(lo[0]) - 1, int(lo[1]) - 1, int(hi[0] - lo[0]) + 4, int(hi[1] - lo[1]) + 4))
    for p in xy:
        sub.insert((float(p[0]), float(p[1])))
    edges = sub.getEdgeList().reshape(-1, 2, 2)
    inside = np.all((edges >= lo) & (edges <= hi), axis=(1, 2))
    return edges[inside]


def _fx(p: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(p) * (1 << _SHIFT)).astype(np.int32)


def _face_panel(image: np.ndarray, face: Face, lm: FaceLandmarks, side: int) -> np.ndarray:
    """The chosen face, upright as found, zoomed to side x side, with its mesh and contours."""
    b = face.detection.box
    cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
    half = 0.8 * max(b[2] - b[0], b[3] - b[1])
    k = side / (2 * half)
    m = np.array([[k, 0, side / 2 - k * cx], [0, k, side / 2 - k * cy]])
    from ..perception.facemesh import warp_region

    panel = warp_region(image, m, cx, cy, 2 * half, side)
    to_panel = lambda p: p @ m[:, :2].T + m[:, 2]  # noqa: E731
    mesh = panel.copy()
    for a, c in _mesh_edges(to_panel(lm.points[:, :2])):
        cv2.line(mesh, tuple(_fx(a)), tuple(_fx(c)), _MESH, 1, cv2.LINE_AA, _SHIFT)
    panel = cv2.addWeighted(mesh, 0.55, panel, 0.45, 0)
    pts = _fx(to_panel(lm.ibug68))
    for idx, closed in _IBUG_LINES:
        cv2.polylines(panel, [pts[list(idx)]], closed, _CONTOUR, 2, cv2.LINE_AA, _SHIFT)
    p = lm.pose
    for i, text in enumerate([f"yaw {p.yaw:+.1f}  pitch {p.pitch:+.1f}  roll {p.roll:+.1f}",
                              f"score {face.detection.score:.2f}  presence {lm.presence:.2f}"]):
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        cv2.rectangle(panel, (4, 6 + 20 * i), (12 + tw, 25 + 20 * i), (0, 0, 0), -1)
        cv2.putText(panel, text, (8, 20 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def draw_detection(image: np.ndarray, det: Detection, height: int = 768) -> np.ndarray:
    """RGB uint8 overlay of ``det`` on ``image`` (H, W, 3) uint8: the photo scaled to ``height`` rows,
    plus, when a face has landmarks, a height x height panel of it on the right."""
    h, w = image.shape[:2]
    k = height / h
    interp = cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR
    vis = cv2.resize(image, (max(int(round(w * k)), 1), height), interpolation=interp)
    thick = 2
    for i, face in enumerate(det.faces):
        colour = _CHOSEN if i == det.chosen else _OTHER
        b = _fx(face.detection.box * k)
        cv2.rectangle(vis, tuple(b[:2]), tuple(b[2:]), colour, thick, cv2.LINE_AA, _SHIFT)
        org = (int(face.detection.box[0] * k), max(int(face.detection.box[1] * k) - 5, 12))
        cv2.putText(vis, f"{face.detection.score:.2f}", org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
        if face.landmarks is not None:
            for p in face.landmarks.points[:, :2] * k:
                cv2.circle(vis, tuple(_fx(p)), 1 << _SHIFT, _MESH, -1, cv2.LINE_AA, _SHIFT)
    if det.chosen is None or det.faces[det.chosen].landmarks is None:
        return vis
    face = det.faces[det.chosen]
    return np.concatenate([vis, _face_panel(image, face, face.landmarks, height)], axis=1)
