"""Region labels on the head: per vertex and as a UV label map, for the photometric mask, the
augmentation's forehead mask and the reflectance data generator."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["REGIONS", "vertex_regions", "uv_region_map", "region_masks"]

# label value -> name; "skin" is the rest of the face
REGIONS = ("scalp", "skin", "forehead", "brows", "eyes", "nose", "lips", "neck")


def _near(v: np.ndarray, anchors: np.ndarray, r: float) -> np.ndarray:
    d2 = ((v[:, None, :] - anchors[None, :, :]) ** 2).sum(-1).min(1)
    return d2 < r * r


def vertex_regions(mean: np.ndarray, face_vertex: np.ndarray, contours: dict[str, np.ndarray]) -> np.ndarray:
    """(V,) uint8 labels (indices into REGIONS). ``face_vertex``: (V,) bool, inside the face oval."""
    v = mean
    ids = lambda k: np.unique(contours[k])  # noqa: E731
    lab = np.full(len(v), REGIONS.index("skin"), np.uint8)
    chin_y = v[152, 1]
    brow_top = max(v[ids("left_eyebrow"), 1].max(), v[ids("right_eyebrow"), 1].max())
    lab[~face_vertex] = REGIONS.index("scalp")
    lab[~face_vertex & (v[:, 1] < chin_y + 5)] = REGIONS.index("neck")
    lab[face_vertex & (v[:, 1] > brow_top + 2)] = REGIONS.index("forehead")
    nose = np.array([1, 2, 4, 5, 6, 19, 94, 168, 195, 197, 45, 275, 48, 278, 64, 294, 98, 327, 129, 358, 102, 331,
                     115, 344, 131, 360, 220, 440, 75, 305, 97, 326, 166, 392, 79, 309, 240, 460])
    lab[face_vertex & _near(v, v[nose], 4.0)] = REGIONS.index("nose")
    lab[face_vertex & _near(v, v[np.concatenate([ids("left_eyebrow"), ids("right_eyebrow")])], 6.0)] = REGIONS.index("brows")
    lab[face_vertex & _near(v, v[ids("lips")], 3.5)] = REGIONS.index("lips")
    lab[face_vertex & _near(v, v[np.concatenate([ids("left_eye"), ids("right_eye")])], 3.0)] = REGIONS.index("eyes")
    return lab


def uv_region_map(labels: np.ndarray, triangles: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray, size: int = 512) -> np.ndarray:
    """(size, size) uint8 label image in UV space (row 0 = v = 1, top, as images are stored); 255 where
    no triangle maps."""
    out = np.full((size, size), 255, np.uint8)
    tri_label = np.array([np.bincount(labels[t], minlength=len(REGIONS)).argmax() for t in triangles], np.uint8)
    px = np.stack([uv[:, 0] * size, (1 - uv[:, 1]) * size], 1)
    for f in range(len(triangles)):
        pts = np.round(px[uv_faces[f]] * 16).astype(np.int32)
        cv2.fillConvexPoly(out, pts, int(tri_label[f]), cv2.LINE_8, 4)
    return out


def region_masks(region_uv: np.ndarray, size: int) -> dict[str, np.ndarray]:
    """{region: (size, size) bool} from the stored UV label map (nearest-neighbour resampling), plus
    "mapped": every texel some triangle covers."""
    lab = cv2.resize(region_uv, (size, size), interpolation=cv2.INTER_NEAREST)
    masks = {name: lab == i for i, name in enumerate(REGIONS)}
    masks["mapped"] = lab != 255
    return masks
