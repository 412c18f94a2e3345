"""Where the photometric loss looks: the skin of the face in the photo.

From the landmarks: the union of FaceMesh's triangles (forehead to chin; FaceMesh leaves the eyes and the
mouth open), minus the eyebrows and the lips, eroded away from the outline. Then a skin-colour model:
a Gaussian in log-chromaticity and log-brightness, fitted robustly to the cheeks and the nose (the band
between the eyes' lower lids and the nose's base), drops what is not skin in the whole mask (fringe,
glasses, a hand, deep shadow or a blown highlight).

Why the band and not the whole mask (2026-11-30): a fringe covers much of the forehead, and a model fitted
to the whole mask took its brown in as skin (the astronaut's bangs, a third of her forehead), so the
tuning painted them into the albedo as a dark blotch (docs/fitting.md, "The skin mask's colour model")."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["SkinMaskSettings", "photo_skin_mask"]


@dataclass(frozen=True)
class SkinMaskSettings:
    erode_fraction: float = 0.02  # of the face width, away from the outline and the holes
    brow_width_fraction: float = 0.05  # eyebrow band thickness, of the face width
    # pixels further than this (Mahalanobis) from the skin colour are dropped. With the cheek band's model, 3 drops
    # 13 % of that band itself on the astronaut (the nose's shadow, under the eyes; 3.5: 8 %, 4: 5 %), but only 3
    # also drops the shadow her bangs cast on her forehead, which the tuning painted purple at 3.5 and 4 (no hair
    # geometry casts it in the render); the likeness did not move (docs/fitting.md, "The skin mask's colour model")
    colour_sigmas: float = 3.0
    use_colour_model: bool = True
    min_model_pixels: int = 64  # fewer in the cheek band (a tiny face): the model is fitted to the whole mask


def _polyline(edges: np.ndarray) -> np.ndarray:
    """Ordered vertex ids of a contour given as (K, 2) edges (possibly several loops: concatenated)."""
    nxt = {int(a): int(b) for a, b in edges}
    out, seen = [], set()
    for start in [int(a) for a, _ in edges]:
        if start in seen:
            continue
        v = start
        while v not in seen and v in nxt:
            seen.add(v)
            out.append(v)
            v = nxt[v]
    return np.array(out)


def photo_skin_mask(rgb: np.ndarray, landmarks: np.ndarray, triangles: np.ndarray, contours: dict[str, np.ndarray],
                    s: SkinMaskSettings = SkinMaskSettings()) -> np.ndarray:
    """rgb: (H, W, 3) uint8; landmarks: (468, 2) pixels; triangles: (852, 3) FaceMesh triangles;
    contours: FaceMesh's contour edges (``read_facemesh_topology().contours``). Returns (H, W) float32
    in {0, 1}."""
    h, w = rgb.shape[:2]
    if landmarks.shape != (468, 2):
        raise ValueError(f"expected (468, 2) landmarks, got {landmarks.shape}")
    face_w = float(np.ptp(landmarks[:, 0])) + 1e-6
    mask = np.zeros((h, w), np.uint8)
    pts = np.round(landmarks * 16).astype(np.int32)
    for tri in triangles:
        cv2.fillConvexPoly(mask, pts[tri], 1, cv2.LINE_8, 4)
    lips = _polyline(contours["lips"])
    cv2.fillPoly(mask, [pts[lips]], 0, cv2.LINE_8, 4)
    brow_w = max(1, int(round(s.brow_width_fraction * face_w)))
    for side in ("left_eyebrow", "right_eyebrow"):
        for a, b in contours[side]:
            cv2.line(mask, tuple(pts[a]), tuple(pts[b]), 0, brow_w, cv2.LINE_8, 4)
    k = max(1, int(round(s.erode_fraction * face_w)))
    mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1)))
    m = mask.astype(bool)
    if s.use_colour_model and m.sum() > s.min_model_pixels:
        x = np.log(rgb[m].astype(np.float64) + 8.0)
        f = np.stack([x[:, 0] - x[:, 1], x[:, 2] - x[:, 1], x.mean(1)], 1)  # two chromaticities, brightness
        band = _cheek_band(landmarks, contours, h, w)[m]
        model = f[band] if band.sum() > s.min_model_pixels else f
        med = np.median(model, 0)
        dev = model - med
        core = np.abs(dev).max(1) < 3 * 1.4826 * np.median(np.abs(dev), 0).max() + 1e-6
        cov = np.cov(model[core].T) + np.eye(3) * 1e-4
        d2 = np.einsum("ni,ij,nj->n", f - med, np.linalg.inv(cov), f - med)
        keep = d2 < s.colour_sigmas**2
        idx = np.flatnonzero(m.ravel())
        flat = m.ravel().copy()
        flat[idx[~keep]] = False
        m = flat.reshape(h, w)
    return m.astype(np.float32)


def _cheek_band(landmarks: np.ndarray, contours: dict[str, np.ndarray], h: int, w: int) -> np.ndarray:
    """(H, W) bool: pixels between the eyes' lowest and the nose's lowest landmark, measured along the face's
    own down axis (eyes' centre to the lips' centre), so a tilted head keeps its band."""
    eyes = np.unique(np.concatenate([contours["left_eye"], contours["right_eye"]]).ravel())
    lips, nose = np.unique(contours["lips"].ravel()), np.unique(contours["nose"].ravel())
    top = landmarks[eyes].mean(0)
    axis = landmarks[lips].mean(0) - top
    axis = axis / max(float(np.linalg.norm(axis)), 1e-6)
    yy, xx = np.mgrid[0:h, 0:w]
    t = (xx - top[0]) * axis[0] + (yy - top[1]) * axis[1]
    return (t > float(((landmarks[eyes] - top) @ axis).max())) & (t < float(((landmarks[nose] - top) @ axis).max()))
