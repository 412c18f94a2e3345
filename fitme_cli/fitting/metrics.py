"""Accuracy of a fit against ground truth (a synthetic subject, ``fitting/synthetic.py``): landmarks in
pixels, shape in millimetres after alignment, albedo as linear L1 and CIE76 Delta E, detail normals in
degrees. Plain functions on numpy arrays or torch tensors; results are typed records.

Every function checks its inputs' shapes and raises ValueError naming what it got and expected.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["ShapeError", "AlbedoError", "FitReport", "landmark_error_px", "rigid_alignment", "point_to_mesh_distance",
           "shape_error_mm", "linear_rgb_to_lab", "albedo_error", "normal_angular_error_deg", "face_vertex_mask",
           "face_uv_mask", "fit_landmarks_px", "evaluate_fit"]

# linear sRGB (Rec. 709 primaries) -> CIE XYZ, D65 white (IEC 61966-2-1)
_RGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                        [0.2126729, 0.7151522, 0.0721750],
                        [0.0193339, 0.1191920, 0.9503041]])
_D65_WHITE = np.array([0.95047, 1.0, 1.08883])  # XYZ of the reference white, Y = 1

# regions (``shape.regions.REGIONS``) that are not the face: the back/top of the head and the neck
_NOT_FACE = ("scalp", "neck")


def _np(x, name: str) -> np.ndarray:
    """A torch tensor or array-like -> float64 numpy (detached, on the CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name}: expected a numeric array, got {type(x).__name__}") from e


def _mask(m, shape: tuple[int, ...], name: str) -> np.ndarray:
    """A bool mask of exactly ``shape`` (leading singleton axes are dropped)."""
    if hasattr(m, "detach"):
        m = m.detach().cpu().numpy()
    m = np.asarray(m)
    while m.ndim > len(shape) and m.shape[0] == 1:
        m = m[0]
    if m.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {m.shape}")
    return m.astype(bool)


# --- landmarks ---------------------------------------------------------------------------------------


def landmark_error_px(pred, target) -> float:
    """Mean Euclidean distance in pixels between corresponding 2-D points.

    pred, target: (N, 2) or (P, N, 2) (P photos of N landmarks, e.g. 68 iBUG or 468 FaceMesh), the same
    shape; numpy or torch. Returns the mean over all points of all photos."""
    p, t = _np(pred, "pred"), _np(target, "target")
    if p.ndim not in (2, 3) or p.shape[-1] != 2:
        raise ValueError(f"landmark_error_px: expected pred of shape (N, 2) or (P, N, 2), got {p.shape}")
    if t.shape != p.shape:
        raise ValueError(f"landmark_error_px: expected target of shape {p.shape} (as pred), got {t.shape}")
    if p.shape[-2] == 0:
        raise ValueError("landmark_error_px: no landmarks")
    return float(np.linalg.norm(p - t, axis=-1).mean())


# --- shape -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ShapeError:
    """Point-to-surface distances (mm) from the aligned predicted vertices to the true mesh.

    mean_mm, median_mm, p95_mm: over the measured vertices; n_points: how many; rotation (3, 3),
    translation (3,) mm and scale: the alignment applied to the prediction, x -> scale R x + t."""

    mean_mm: float
    median_mm: float
    p95_mm: float
    n_points: int
    rotation: np.ndarray
    translation: np.ndarray
    scale: float


def rigid_alignment(src, dst, similarity: bool = False, weights=None) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (Kabsch / Umeyama) alignment of corresponding points: R, t, s minimising
    sum_i w_i |s R src_i + t - dst_i|^2, with s = 1 unless ``similarity``. src, dst: (N, 3), N >= 3;
    weights: (N,) >= 0 or None. Returns (R (3, 3) proper rotation, t (3,), s)."""
    a, b = _np(src, "src"), _np(dst, "dst")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"rigid_alignment: expected src of shape (N, 3), got {a.shape}")
    if b.shape != a.shape:
        raise ValueError(f"rigid_alignment: expected dst of shape {a.shape} (as src), got {b.shape}")
    if len(a) < 3:
        raise ValueError(f"rigid_alignment: need at least 3 points, got {len(a)}")
    w = np.ones(len(a)) if weights is None else _np(weights, "weights")
    if w.shape != (len(a),) or (w < 0).any() or w.sum() <= 0:
        raise ValueError(f"rigid_alignment: expected weights of shape ({len(a)},), >= 0, not all 0; got {w.shape}")
    w = w / w.sum()
    ma, mb = w @ a, w @ b
    ac, bc = a - ma, b - mb
    cov = (bc * w[:, None]).T @ ac  # (3, 3) sum w (dst)(src)^T
    u, sv, vt = np.linalg.svd(cov)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(d) @ vt
    scale = 1.0
    if similarity:
        var = float((w * (ac**2).sum(1)).sum())
        scale = float((sv * d).sum() / var) if var > 0 else 1.0
    return rot, mb - scale * rot @ ma, scale


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to points p, all (..., 3) broadcast (Ericson, Real-Time
    Collision Detection 5.1.5, vectorised: the Voronoi regions' answers overwrite each other in
    reverse order of the scalar code's early returns)."""
    def dot(x, y):
        return (x * y).sum(-1)

    def div(n, d):
        return n / np.where(np.abs(d) > 1e-30, d, 1e-30)

    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    v, w = div(vb, denom), div(vc, denom)
    out = a + ab * v[..., None] + ac * w[..., None]  # inside the face
    e = (d4 - d3) + (d5 - d6)
    sel = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)  # edge BC
    out = np.where(sel[..., None], b + (c - b) * div(d4 - d3, e)[..., None], out)
    sel = (vb <= 0) & (d2 >= 0) & (d6 <= 0)  # edge AC
    out = np.where(sel[..., None], a + ac * div(d2, d2 - d6)[..., None], out)
    sel = (d6 >= 0) & (d5 <= d6)  # vertex C
    out = np.where(sel[..., None], c, out)
    sel = (vc <= 0) & (d1 >= 0) & (d3 <= 0)  # edge AB
    out = np.where(sel[..., None], a + ab * div(d1, d1 - d3)[..., None], out)
    sel = (d3 >= 0) & (d4 <= d3)  # vertex B
    out = np.where(sel[..., None], b, out)
    sel = (d1 <= 0) & (d2 <= 0)  # vertex A
    return np.where(sel[..., None], a, out)


def point_to_mesh_distance(points, vertices, faces, k_nearest: int = 8, chunk: int = 4096) -> np.ndarray:
    """(Q,) distances from points (Q, 3) to the surface of the mesh (vertices (V, 3), faces (F, 3)).

    Candidate search: the triangles incident to each point's ``k_nearest`` nearest mesh vertices (a
    KD-tree), then an exact point-to-triangle distance to each candidate. On a mesh of roughly even
    triangles this finds the true nearest triangle; otherwise it returns an upper bound."""
    from scipy.spatial import cKDTree

    q, v = _np(points, "points"), _np(vertices, "vertices")
    f = np.asarray(faces.detach().cpu().numpy() if hasattr(faces, "detach") else faces)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"point_to_mesh_distance: expected points of shape (Q, 3), got {q.shape}")
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"point_to_mesh_distance: expected vertices of shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu" or len(f) == 0:
        raise ValueError(f"point_to_mesh_distance: expected integer faces of shape (F, 3), F > 0, got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"point_to_mesh_distance: face indices must be in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    f = f.astype(np.int64)
    # vertex -> incident faces, as CSR: faces_of[start[v] : start[v] + count[v]]
    corner_v = f.reshape(-1)
    order = np.argsort(corner_v, kind="stable")
    faces_of = np.repeat(np.arange(len(f)), 3)[order]
    count = np.bincount(corner_v, minlength=len(v))
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    k = int(min(max(1, k_nearest), len(v)))
    _, near = cKDTree(v).query(q, k=k)
    near = near.reshape(len(q), k)
    out = np.full(len(q), np.inf)
    for s in range(0, len(q), chunk):
        nv = near[s:s + chunk].reshape(-1)  # (C k,) nearest vertices, query-major
        cnt = count[nv]
        total = int(cnt.sum())
        if total == 0:
            continue
        first = np.cumsum(cnt) - cnt  # where each vertex's faces begin in the flat candidate list
        cand = faces_of[np.repeat(start[nv] - first, cnt) + np.arange(total)]  # (M,) candidate faces
        per_query = cnt.reshape(-1, k).sum(1)
        qid = np.repeat(np.arange(len(per_query)), per_query)
        p = q[s + qid]
        tri = f[cand]
        d = np.linalg.norm(_closest_on_triangles(p, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]) - p, axis=-1)
        has = per_query > 0
        bounds = (np.cumsum(per_query) - per_query)[has]
        out[s:s + chunk][has] = np.minimum.reduceat(d, bounds)
    return out


def shape_error_mm(pred_vertices, true_vertices, faces, mask=None,
                   alignment: Literal["rigid", "similarity", "none"] = "rigid", k_nearest: int = 8) -> ShapeError:
    """Shape error of a predicted mesh against the true one (same topology), in mm.

    pred_vertices, true_vertices: (V, 3) mm (numpy or torch); faces: (F, 3) the true mesh's triangles;
    mask: (V,) bool, the vertices measured (and used for the alignment), e.g. ``face_vertex_mask`` to
    leave out the back of the head and the neck; None: all. ``alignment``: "rigid" (rotation +
    translation, Kabsch on the masked vertex correspondences), "similarity" (also a uniform scale,
    Umeyama) or "none". Then each aligned predicted vertex's distance to the true surface
    (``point_to_mesh_distance``): mean, median and 95th percentile."""
    p, t = _np(pred_vertices, "pred_vertices"), _np(true_vertices, "true_vertices")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"shape_error_mm: expected true_vertices of shape (V, 3), got {t.shape}")
    if p.shape != t.shape:
        raise ValueError(f"shape_error_mm: expected pred_vertices of shape {t.shape} (as true_vertices), got {p.shape}")
    if alignment not in ("rigid", "similarity", "none"):
        raise ValueError(f"shape_error_mm: alignment must be 'rigid', 'similarity' or 'none', got {alignment!r}")
    m = np.ones(len(t), bool) if mask is None else _mask(mask, (len(t),), "shape_error_mm: mask")
    if m.sum() < 3:
        raise ValueError(f"shape_error_mm: the mask selects {int(m.sum())} vertices, need at least 3")
    if alignment == "none":
        rot, tr, sc = np.eye(3), np.zeros(3), 1.0
    else:
        rot, tr, sc = rigid_alignment(p[m], t[m], similarity=alignment == "similarity")
    aligned = sc * p[m] @ rot.T + tr
    d = point_to_mesh_distance(aligned, t, faces, k_nearest)
    return ShapeError(float(d.mean()), float(np.median(d)), float(np.percentile(d, 95)), int(m.sum()), rot, tr, sc)


# --- albedo and normals ------------------------------------------------------------------------------


@dataclass(frozen=True)
class AlbedoError:
    """Albedo error over the masked texels. l1_linear: mean |pred - true| over texels and channels
    (linear RGB); delta_e: mean CIE76 Delta E (Lab, D65). The ``_gain`` values are the same after the
    per-channel least-squares gain ``gain`` (3,) is applied to the prediction: albedo and light
    intensity (and colour) trade off exactly in a render, so only albedo up to a per-channel scale is
    observable from photos."""

    l1_linear: float
    delta_e: float
    l1_linear_gain: float
    delta_e_gain: float
    gain: np.ndarray


def linear_rgb_to_lab(rgb) -> np.ndarray:
    """(..., 3) linear sRGB (Rec. 709 primaries, 1 = reference white) -> (..., 3) CIE L*a*b* (D65):
    linear RGB -> XYZ -> Lab (CIE 1976)."""
    x = _np(rgb, "rgb")
    if x.shape[-1:] != (3,):
        raise ValueError(f"linear_rgb_to_lab: expected shape (..., 3), got {x.shape}")
    xyz = x @ _RGB_TO_XYZ.T / _D65_WHITE
    eps = (6 / 29) ** 3
    f = np.where(xyz > eps, np.cbrt(np.maximum(xyz, eps)), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def _texels(x, name: str, channels: int) -> np.ndarray:
    """(1, C, R, R) or (C, R, R) -> (C, R, R) float64."""
    a = _np(x, name)
    if a.ndim == 4 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 3 or a.shape[0] != channels:
        raise ValueError(f"{name}: expected shape (1, {channels}, R, R) or ({channels}, R, R), got {_np(x, name).shape}")
    return a


def albedo_error(pred_albedo, true_albedo, mask=None) -> AlbedoError:
    """Albedo error over the masked texels (see ``AlbedoError``; errors are reported both as given and
    after a per-channel least-squares gain on the prediction, since albedo scale is ambiguous with
    light intensity).

    pred_albedo, true_albedo: (1, 3, R, R) or (3, R, R) linear RGB (numpy or torch), the same R;
    mask: (R, R) bool (e.g. ``face_uv_mask``) or None for every texel."""
    p, t = _texels(pred_albedo, "albedo_error: pred_albedo", 3), _texels(true_albedo, "albedo_error: true_albedo", 3)
    if p.shape != t.shape:
        raise ValueError(f"albedo_error: expected pred_albedo of shape {t.shape} (as true_albedo), got {p.shape}")
    m = np.ones(t.shape[1:], bool) if mask is None else _mask(mask, t.shape[1:], "albedo_error: mask")
    if not m.any():
        raise ValueError("albedo_error: the mask selects no texels")
    pv, tv = p[:, m].T, t[:, m].T  # (N, 3)
    pp = (pv * pv).sum(0)
    gain = np.where(pp > 0, (pv * tv).sum(0) / np.where(pp > 0, pp, 1), 1.0)
    lab_t = linear_rgb_to_lab(tv)

    def errs(x):
        return float(np.abs(x - tv).mean()), float(np.linalg.norm(linear_rgb_to_lab(x) - lab_t, axis=-1).mean())

    l1, de = errs(pv)
    l1g, deg = errs(pv * gain)
    return AlbedoError(l1, de, l1g, deg, gain)


def normal_angular_error_deg(pred_normals, true_normals, mask=None) -> float:
    """Mean angle in degrees between corresponding normals (each normalised first).

    Either maps: (1, 3, R, R) or (3, R, R) with mask (R, R) bool or None; or vectors: (N, 3) with mask
    (N,) bool or None."""
    p, t = _np(pred_normals, "pred_normals"), _np(true_normals, "true_normals")
    if t.ndim == 2 and t.shape[1] == 3:
        if p.shape != t.shape:
            raise ValueError(f"normal_angular_error_deg: expected pred_normals of shape {t.shape} (as true_normals), got {p.shape}")
        m = np.ones(len(t), bool) if mask is None else _mask(mask, (len(t),), "normal_angular_error_deg: mask")
        pv, tv = p[m], t[m]
    else:
        t = _texels(t, "normal_angular_error_deg: true_normals", 3)
        p = _texels(p, "normal_angular_error_deg: pred_normals", 3)
        if p.shape != t.shape:
            raise ValueError(f"normal_angular_error_deg: expected pred_normals of shape {t.shape} (as true_normals), got {p.shape}")
        m = np.ones(t.shape[1:], bool) if mask is None else _mask(mask, t.shape[1:], "normal_angular_error_deg: mask")
        pv, tv = p[:, m].T, t[:, m].T
    if len(tv) == 0:
        raise ValueError("normal_angular_error_deg: the mask selects nothing")
    cross = np.linalg.norm(np.cross(pv, tv), axis=-1)
    dot = (pv * tv).sum(-1)
    return float(np.degrees(np.arctan2(cross, dot)).mean())  # atan2: accurate at small angles, scale-free


# --- masks and a fit's summary -----------------------------------------------------------------------


def face_vertex_mask(shape_model) -> np.ndarray:
    """(V,) bool: the shape model's face vertices (every region except the scalp / back of the head and
    the neck), from its per-vertex region labels."""
    from ..shape.regions import REGIONS

    lab = shape_model.regions.detach().cpu().numpy() if hasattr(shape_model.regions, "detach") else np.asarray(shape_model.regions)
    return ~np.isin(lab, [REGIONS.index(r) for r in _NOT_FACE])


def face_uv_mask(shape_model, resolution: int) -> np.ndarray:
    """(R, R) bool: texels of the face in the UV layout (mapped by a triangle and not scalp or neck),
    at the maps' resolution R."""
    from ..shape.regions import region_masks

    if resolution < 1:
        raise ValueError(f"face_uv_mask: resolution must be positive, got {resolution}")
    ru = shape_model.region_uv
    ru = ru.detach().cpu().numpy() if hasattr(ru, "detach") else np.asarray(ru)
    masks = region_masks(ru.astype(np.uint8), resolution)
    out = masks["mapped"].copy()
    for r in _NOT_FACE:
        out &= ~masks[r]
    return out


def fit_landmarks_px(shape_model, p_s, p_e, cameras, to_photo, vertex_ids=None) -> np.ndarray:
    """(P, N, 2) photo pixels of a fit's landmark vertices: the fitted mesh of each photo (p_s (1, K),
    p_e (P, E)) projected through the fitted cameras (crop pixels, as ``invert`` returns them) and
    mapped to the photo by each ``PhotoInput.to_photo`` ((P, 2, 3) or a list of (2, 3)).
    ``vertex_ids``: (N,) mesh vertices, default the iBUG-68 ones (``shape_model.ibug68``)."""
    import torch

    from ..render.camera import project

    a = _np(np.stack([_np(x, "to_photo") for x in to_photo]) if isinstance(to_photo, (list, tuple)) else to_photo, "to_photo")
    if a.ndim != 3 or a.shape[1:] != (2, 3) or a.shape[0] != cameras.batch:
        raise ValueError(f"fit_landmarks_px: expected to_photo of shape ({cameras.batch}, 2, 3), got {a.shape}")
    ids = shape_model.ibug68 if vertex_ids is None else torch.as_tensor(np.asarray(vertex_ids), dtype=torch.long)
    with torch.no_grad():
        v = shape_model.vertices(p_s.expand(cameras.batch, -1), p_e)
        px = project(v[:, ids.to(v.device)], cameras)[..., :2].cpu().numpy().astype(np.float64)
    return np.einsum("pij,pnj->pni", a[:, :, :2], px) + a[:, None, :, 2]


@dataclass(frozen=True)
class FitReport:
    """A fit scored against a synthetic subject. landmark_px: iBUG-68 landmark vertices of the fit vs
    their true projections, photo pixels, mean over photos; shape: the neutral identity meshes (p_s
    only), face region, rigid alignment; shape_posed: each photo's posed mesh (p_s and its p_e), mean
    of the per-photo errors; albedo: face texels; normals_deg: detail normals on the face texels."""

    landmark_px: float
    shape: ShapeError
    shape_posed_mean_mm: float
    albedo: AlbedoError
    normals_deg: float


def evaluate_fit(subject, shape_model, p_s, p_e, cameras, maps, to_photo) -> FitReport:
    """Score a fit (p_s (1, K), p_e (P, E), cameras batch P in crop pixels, maps ReflectanceMaps,
    to_photo per photo) against a ``SyntheticSubject`` seen in the same P photos."""
    import torch

    if p_e.shape[0] != subject.n_views:
        raise ValueError(f"evaluate_fit: the fit has {p_e.shape[0]} photos, the subject {subject.n_views} views")
    lm = fit_landmarks_px(shape_model, p_s, p_e, cameras, to_photo)
    face = face_vertex_mask(shape_model)
    tri = shape_model.triangles.cpu().numpy()
    with torch.no_grad():
        neutral = shape_model.vertices(p_s, torch.zeros_like(p_e[:1]))[0]
        posed = shape_model.vertices(p_s.expand(subject.n_views, -1), p_e)
    shape = shape_error_mm(neutral, subject.neutral, tri, face)
    posed_err = float(np.mean([shape_error_mm(posed[i], subject.vertices[i], tri, face).mean_mm for i in range(subject.n_views)]))
    r = maps.albedo.shape[-1]
    if subject.maps.albedo.shape[-1] != r:
        raise ValueError(f"evaluate_fit: maps of resolution {r}, the subject's are {subject.maps.albedo.shape[-1]}")
    uv = face_uv_mask(shape_model, r)
    return FitReport(landmark_error_px(lm, subject.ibug68), shape, posed_err, albedo_error(maps.albedo, subject.maps.albedo, uv),
                     normal_angular_error_deg(maps.normals, subject.maps.normals, uv))
