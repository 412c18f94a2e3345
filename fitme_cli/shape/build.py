"""Build the shape model from code: topology, mean shape (mm), Gaussian-process identity basis.

Steps (all deterministic):
1. Face topology: MediaPipe FaceMesh's own 852 triangles over its 468 landmarks (vertex i = landmark i),
   with 3 edge flips that make it exactly mirror-symmetric (MediaPipe's canonical mesh is not quite).
2. Mean face: FaceMesh's 3D predictions on real frontal photos shipped in PyPI packages (scikit-image's
   astronaut, matplotlib's Grace Hopper) and their mirror images, each put in its face frame, scaled to
   an interpupillary distance of 63 mm, averaged, symmetrised, rounded to 0.01 mm; lips closed.
3. Head: rings from the face oval to a pole at the back of the head, projected onto an implicit
   head-and-neck surface (an anthropometric ellipsoid, breadth 152 mm, length 192 mm, smoothly united
   with a round-ended neck cylinder) and blended into the face. Closed but for the eye and mouth holes.
4. Refinement: two Loop subdivisions (smooth); vertex i stays landmark i. The face-oval controls are
   solved so that the surface passes exactly through the mean outline (the head's smoothing would
   pull the chin by 6 mm); interior landmarks are smoothed by ~1 mm, like the rest. Solving for every
   landmark bends the surface at FaceMesh's near-coincident landmarks into slivers (min angle 1.9
   degrees instead of 5.9). Every fine vertex is a fixed linear combination of the coarse ones (S).
5. Identity basis: a Gaussian-process morphable model (Luthi et al. 2018) on the coarse mesh: a sum of
   three Gaussian kernels (coarse/medium/fine scales) with left-right coupling, eigen-decomposed per
   coordinate (so the basis does not depend on the BLAS thread count), lifted to the fine mesh by S and
   re-orthonormalised there.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ModelBuildError

__all__ = ["ShapeBuildSettings", "build"]

NAME = "shape_model"
IPD_MM = 63.0


@dataclass(frozen=True)
class ShapeBuildSettings:
    head_breadth_mm: float = 152.0  # euryon-euryon, adult mean (both sexes)
    head_length_mm: float = 192.0  # glabella-opisthocranion
    vertex_above_forehead_mm: float = 62.0  # head top above FaceMesh's top forehead point (10)
    rings: int = 10  # coarse rings from the face oval to the back pole
    neck_radii_mm: tuple[float, float] = (54.0, 58.0)  # half width, half depth (adult neck ~ 110 x 116 mm)
    neck_length_mm: float = 85.0  # below the chin, to a rounded end
    neck_behind_chin_mm: float = 68.0  # neck axis behind the chin
    subdivisions: int = 2
    # GP kernel: (std mm, length scale mm) per scale, and the left-right correlation of the deformation
    scales: tuple[tuple[float, float], ...] = ((3.0, 90.0), (1.5, 40.0), (0.6, 15.0))
    symmetry: float = 0.85
    components: int = 100
    # Which landmarks the smooth surface must pass through exactly: "all", "oval" (the face outline,
    # where the head's smoothing would otherwise pull the chin and jaw by up to 6 mm) or "none".
    interpolate_landmarks: str = "oval"


# ---------------------------------------------------------------- mean face from real photos


def _facemesh_shapes(root: Path) -> list[np.ndarray]:
    """FaceMesh landmarks of real frontal faces and their mirror images, in each face's own frame
    (model axes: x to the subject's left = image right, y up, z toward the viewer), IPD-normalised later."""
    from ..io import sample_photo
    from ..perception.detect import DetectSettings, detect
    from ..perception.head_pose import face_rotation

    out = []
    for name in ("astronaut", "grace_hopper"):
        rgb = sample_photo(name).rgb
        for flip in (False, True):
            img = np.ascontiguousarray(rgb[:, ::-1]) if flip else rgb
            p = detect(img, DetectSettings(identity=False), root).face.landmarks.points.astype(np.float64)
            q = ((p - p.mean(0)) @ face_rotation(p)) * [1.0, -1.0, -1.0]
            if flip:
                q[:, 0] *= -1.0  # un-mirror: now landmark i of the flipped photo lies where the mirror of i is
            out.append(q)
    return out


def _mirror_map(shapes: list[np.ndarray]) -> np.ndarray:
    """mirror[i] = the landmark at the mirror place of landmark i, from photos and their flips."""
    from scipy.optimize import linear_sum_assignment

    a = np.mean(shapes[0::2], axis=0)
    b = np.mean(shapes[1::2], axis=0)
    cost = np.linalg.norm(b[:, None, :2] - a[None, :, :2], axis=2)
    _, mirror = linear_sum_assignment(cost)
    if not np.array_equal(mirror[mirror], np.arange(len(mirror))):
        raise ModelBuildError("FaceMesh mirror map is not an involution")
    return mirror


def _flip_edge(tri: np.ndarray, a: int, b: int) -> np.ndarray:
    idx = [i for i, t in enumerate(tri) if a in t and b in t]
    if len(idx) != 2:
        raise ModelBuildError(f"edge ({a}, {b}) is not interior")
    t1, t2 = tri[idx[0]].tolist(), tri[idx[1]].tolist()
    c = next(v for v in t1 if v not in (a, b))
    d = next(v for v in t2 if v not in (a, b))
    i = t1.index(c)
    _, x, y = t1[i:] + t1[:i]
    out = tri.copy()
    out[idx[0]], out[idx[1]] = [c, x, d], [c, d, y]
    return out


def _edges(tri: np.ndarray) -> set[tuple[int, int]]:
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    return set(map(tuple, np.sort(e, axis=1).tolist()))


def _symmetrise_topology(tri: np.ndarray, mirror: np.ndarray, x: np.ndarray) -> np.ndarray:
    edges = _edges(tri)
    bad = [(a, b) for a, b in edges if tuple(sorted((mirror[a], mirror[b]))) not in edges]
    for a, b in bad:
        if x[a] + x[b] > 0:  # flip the subject's-left copy to match its mirror
            tri = _flip_edge(tri, a, b)
    if set(map(tuple, np.sort(tri, 1).tolist())) != set(map(tuple, np.sort(mirror[tri], 1).tolist())):
        raise ModelBuildError("could not make the FaceMesh triangulation mirror-symmetric")
    return tri


def _min_angle(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(F,) smallest interior angle of each triangle, degrees."""
    out = np.full(len(tri), 180.0)
    for i in range(3):
        a, b, c = p[tri[:, i]], p[tri[:, (i + 1) % 3]], p[tri[:, (i + 2) % 3]]
        u, w = b - a, c - a
        cos = (u * w).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1) + 1e-12)
        out = np.minimum(out, np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return out


def _mirror_points(p: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    return p[mirror] * [-1.0, 1.0, 1.0]


# ---------------------------------------------------------------- the head beyond the face


def _loop(edges: np.ndarray) -> np.ndarray:
    """Order a closed contour given as (E, 2) edges into a vertex loop."""
    nxt: dict[int, list[int]] = {}
    for a, b in edges.tolist():
        nxt.setdefault(a, []).append(b)
        nxt.setdefault(b, []).append(a)
    start = min(nxt)
    loop, prev = [start], None
    while True:
        cur = loop[-1]
        cand = [v for v in nxt[cur] if v != prev]
        step = min(cand) if prev is None else cand[0]
        if step == start:
            break
        prev = cur
        loop.append(step)
    return np.asarray(loop)


@dataclass(frozen=True)
class _Head:
    centre: np.ndarray
    ax: float
    ay_top: float
    ay_bottom: float
    az: float

    def point(self, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """Ellipsoid point at polar angle alpha from the front (+z) axis, azimuth beta around it."""
        u = np.stack([np.sin(alpha) * np.cos(beta), np.sin(alpha) * np.sin(beta), np.cos(alpha)], -1)
        ay = np.where(u[..., 1] >= 0, self.ay_top, self.ay_bottom)
        return self.centre + u * np.stack([np.full_like(ay, self.ax), ay, np.full_like(ay, self.az)], -1)

    def angles(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = p - self.centre
        ay = np.where(d[:, 1] >= 0, self.ay_top, self.ay_bottom)
        u = d / np.stack([np.full_like(ay, self.ax), ay, np.full_like(ay, self.az)], -1)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return np.arccos(np.clip(u[:, 2], -1, 1)), np.arctan2(u[:, 1], u[:, 0])


def _head_and_neck(head: _Head, chin: np.ndarray, s: ShapeBuildSettings):
    """Implicit head+neck: smooth union of the head ellipsoid and a vertical, round-ended neck cylinder.
    Returns f(p) (< 0 inside), in units of the ellipsoid's radii."""
    rx, rz = s.neck_radii_mm
    axis_z = chin[2] - s.neck_behind_chin_mm
    bottom = chin[1] - s.neck_length_mm

    def f(p: np.ndarray) -> np.ndarray:
        d = p - head.centre
        ay = np.where(d[:, 1] >= 0, head.ay_top, head.ay_bottom)
        ell = np.sqrt((d[:, 0] / head.ax) ** 2 + (d[:, 1] / ay) ** 2 + (d[:, 2] / head.az) ** 2) - 1
        side = np.sqrt((p[:, 0] / rx) ** 2 + ((p[:, 2] - axis_z) / rz) ** 2) - 1
        end = np.maximum(bottom - p[:, 1], p[:, 1] - head.centre[1]) / 40.0  # ends inside the head
        cyl = np.where(end > 0, np.sqrt(np.maximum(side, 0) ** 2 + end**2), np.maximum(side, end))
        k = 0.12  # blend width: a smooth jaw-to-neck transition
        return -k * np.logaddexp(-ell / k, -cyl / k)

    return f


def _project_star(points: np.ndarray, centre: np.ndarray, f) -> np.ndarray:
    """Move each point along the ray from ``centre`` onto f = 0 (bisection; the shape is star-shaped)."""
    d = points - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = np.zeros(len(d)), np.full(len(d), 400.0)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        inside = f(centre + d * mid[:, None]) < 0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return centre + d * (0.5 * (lo + hi))[:, None]


def _complete_head(face: np.ndarray, oval: np.ndarray, eyes: np.ndarray, s: ShapeBuildSettings):
    """Vertices and triangles of the head beyond the face oval. Returns (points, triangles, ring ids)."""
    eye_y = face[eyes, 1].mean()
    top = face[10, 1] + s.vertex_above_forehead_mm
    chin = face[152, 1]
    side_z = face[[234, 454], 2].mean()  # FaceMesh's outermost cheek points, just in front of the ears
    head = _Head(
        centre=np.array([0.0, eye_y, side_z - 0.12 * s.head_length_mm]),
        ax=s.head_breadth_mm / 2,
        ay_top=top - eye_y,
        ay_bottom=(eye_y - chin) + 8.0,
        az=s.head_length_mm / 2,
    )
    alpha0, beta = head.angles(face[oval])
    shape = _head_and_neck(head, face[152], s)
    surface = lambda a, b: _project_star(head.point(a, b), head.centre, shape)  # noqa: E731
    offset = face[oval] - surface(alpha0, beta)
    n = len(oval)
    rings = []
    for r in range(1, s.rings):
        t = r / s.rings
        alpha = alpha0 + (np.pi - alpha0) * t
        w = max(0.0, 1.0 - r / 3.0) ** 2  # the face's own shape fades out over 3 rings
        rings.append(surface(alpha, beta) + w * offset)
    pole = surface(np.array([np.pi]), np.array([0.0]))
    pts = np.concatenate(rings + [pole])
    base = face.shape[0]
    ring_ids = [oval] + [base + r * n + np.arange(n) for r in range(len(rings))]
    pole_id = base + len(rings) * n
    x_mid = face[oval, 0]
    tris = []
    for a_ids, b_ids in zip(ring_ids[:-1], ring_ids[1:]):
        for j in range(n):
            k = (j + 1) % n
            a0, a1, b0, b1 = a_ids[j], a_ids[k], b_ids[j], b_ids[k]
            if x_mid[j] + x_mid[k] >= 0:  # mirror-symmetric diagonals
                tris += [[a0, b0, b1], [a0, b1, a1]]
            else:
                tris += [[a0, b0, a1], [a1, b0, b1]]
    last = ring_ids[-1]
    tris += [[last[j], pole_id, last[(j + 1) % n]] for j in range(n)]
    return pts, np.asarray(tris, np.int64)


# ---------------------------------------------------------------- subdivision


def _subdivide(tri: np.ndarray, n_vertices: int, pinned: int):
    """One Loop subdivision: (sparse S, new triangles). New vertex on edge (a, b) with opposite vertices
    c, d = 3/8 (a + b) + 1/8 (c + d); boundary edges: midpoint. Old vertices move by Loop's vertex rule
    (boundary: 3/4 v + 1/8 (two boundary neighbours)), except the first ``pinned`` (the landmarks), which
    stay where they are so that vertex i remains landmark i."""
    import scipy.sparse as sp

    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    opp = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
    key = np.sort(e, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    m = len(uniq)
    opps: list[list[int]] = [[] for _ in range(m)]
    for i, o in zip(inv.tolist(), opp.tolist()):
        opps[i].append(o)
    nbrs: list[set[int]] = [set() for _ in range(n_vertices)]
    bnbrs: list[list[int]] = [[] for _ in range(n_vertices)]
    for i, (a, b) in enumerate(uniq.tolist()):
        nbrs[a].add(b)
        nbrs[b].add(a)
        if len(opps[i]) == 1:
            bnbrs[a].append(b)
            bnbrs[b].append(a)
    rows, cols, vals = [], [], []
    for v in range(n_vertices):
        if v < pinned or not nbrs[v]:
            rows.append(v), cols.append(v), vals.append(1.0)
        elif bnbrs[v]:
            rows += [v] * 3
            cols += [v, *bnbrs[v][:2]]
            vals += [0.75, 0.125, 0.125]
        else:
            k = len(nbrs[v])
            beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / k) / 4) ** 2) / k
            rows += [v] * (k + 1)
            cols += [v, *sorted(nbrs[v])]
            vals += [1 - k * beta] + [beta] * k
    for i, (a, b) in enumerate(uniq.tolist()):
        r = n_vertices + i
        if len(opps[i]) == 2:
            rows += [r] * 4
            cols += [a, b, opps[i][0], opps[i][1]]
            vals += [3 / 8, 3 / 8, 1 / 8, 1 / 8]
        else:
            rows += [r, r]
            cols += [a, b]
            vals += [0.5, 0.5]
    S = sp.csr_matrix((vals, (rows, cols)), shape=(n_vertices + m, n_vertices))
    mid = (n_vertices + inv).reshape(3, -1).T  # per triangle: edges (0,1), (1,2), (2,0)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    m01, m12, m20 = mid[:, 0], mid[:, 1], mid[:, 2]
    new = np.concatenate([
        np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1), np.stack([m20, m12, c], 1), np.stack([m01, m12, m20], 1)
    ])
    return S, new


# ---------------------------------------------------------------- GP basis


def _gp_kernels(x: np.ndarray, s: ShapeBuildSettings) -> tuple[np.ndarray, np.ndarray]:
    """The (N, N) covariances (mm²) of the displacement field's x coordinate and of its y (= z) coordinate.

    The field's covariance is K(x, y) = k(x, y) I + rho k(x, R y) R with R = diag(-1, 1, 1) and k a sum
    of isotropic Gaussians. For rho = 1 it is the covariance of the symmetrised field f(x) + R f(Rx) of an
    independent GP f ~ GP(0, k I); for 0 <= rho <= 1 it mixes that with an independent field, so it stays
    positive semi-definite. rho sets how symmetric faces are. K is block-diagonal over the coordinates,
    and its y and z blocks are the same matrix."""
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    xm = x * [-1.0, 1.0, 1.0]
    d2m = ((x[:, None, :] - xm[None, :, :]) ** 2).sum(-1)
    k = sum(sd**2 * np.exp(-d2 / (2 * ls**2)) for sd, ls in s.scales)
    km = sum(sd**2 * np.exp(-d2m / (2 * ls**2)) for sd, ls in s.scales)
    return k - s.symmetry * km, k + s.symmetry * km


def _identity_basis(coarse: np.ndarray, S, s: ShapeBuildSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(basis (3 n_fine, k) orthonormal, its eigenvalues (k,) mm² descending, all 3N coarse eigenvalues).

    Each coordinate is diagonalised on its own, and y and z share one computation. Diagonalising the
    whole (3N, 3N) K made the basis depend on the BLAS thread count: every y eigenvalue equals a z one,
    so eigh returned an arbitrary rotation of each y/z pair (1 thread against 2 differed by up to 2x the
    basis's largest entry, 2026-11-28), and even two eigh calls on the y and z blocks in one process
    differ in the last bits, which swapped y and z in the ranking. Now each basis vector moves one
    coordinate, y/z ties are exact, and equal eigenvalues rank x, y, z."""
    n = len(coarse)
    blocks = [np.linalg.eigh(b) for b in _gp_kernels(coarse, s)]
    lam_c = [blocks[0][0][::-1], blocks[1][0][::-1], blocks[1][0][::-1]]
    all_lam = np.concatenate(lam_c)
    chan = np.repeat(np.arange(3), n)
    pick = np.lexsort((chan, -all_lam))[: s.components]  # by eigenvalue, then coordinate
    n_kept = [int(np.sum(chan[pick] == c)) for c in range(3)]
    n_fine = S.shape[0]
    vecs, vals, chans = [], [], []
    # lift each block's kept components to the fine mesh and re-orthonormalise there; y and z keep the
    # same (larger) set and are truncated by fine eigenvalue below, so their fine eigenpairs are the same
    for (lam, u), m, coords in ((blocks[0], n_kept[0], (0,)), (blocks[1], max(n_kept[1:]), (1, 2))):
        if m == 0:
            continue
        lam, u = lam[::-1][:m], u[:, ::-1][:, :m]
        q, r = np.linalg.qr(S @ (u * np.sqrt(lam)))  # the fine covariance's square root
        lam_f, rot = np.linalg.eigh(r @ r.T)
        fine = q @ rot
        for c in coords:
            v = np.zeros((n_fine, 3, m))
            v[:, c, :] = fine
            vecs.append(v.reshape(3 * n_fine, m))
            vals.append(lam_f)
            chans.append(np.full(m, c))
    vecs, vals, chans = np.concatenate(vecs, 1), np.concatenate(vals), np.concatenate(chans)
    order = np.lexsort((chans, -vals))[: s.components]
    return _fix_signs(vecs[:, order]), vals[order], np.sort(all_lam)[::-1]


def _fix_signs(u: np.ndarray) -> np.ndarray:
    """Deterministic eigenvector signs: each column's dot product with the ramp 1..M is positive.

    Not the sign of the largest entry: on the mirror-symmetric head, a symmetric or antisymmetric vector
    has its largest magnitude at a mirror pair of vertices, and which of the two argmax picks flipped
    with the BLAS thread count. The ramp follows the vertex order, which is not mirror-symmetric."""
    d = np.arange(1, len(u) + 1, dtype=np.float64) @ u
    if np.any(np.abs(d) < 1e-6 * np.abs(u).sum(0) * len(u)):
        raise ModelBuildError("an identity basis vector is orthogonal to the sign-fixing ramp")
    return u * np.sign(d)


# ---------------------------------------------------------------- UVs


def _cylindrical_uvs(v: np.ndarray, tri: np.ndarray, centre_z: float):
    """u = 0.5 + atan2(x, z - c)/(2 pi) (face centred at u = 0.5, mirror-symmetric about it), v by height.
    Triangles across the seam at the back get duplicated UV vertices. Returns (uv (T, 2), uv_faces (F, 3))."""
    u = 0.5 + np.arctan2(v[:, 0], v[:, 2] - centre_z) / (2 * np.pi)
    y = v[:, 1]
    vv = (y - y.min()) / (y.max() - y.min())
    uv = np.stack([u, vv], 1)
    uv_faces = tri.copy()
    extra = []
    for f in range(len(tri)):
        us = u[tri[f]]
        if us.max() - us.min() > 0.5:
            for c in range(3):
                if us[c] < 0.5:
                    extra.append([uv[tri[f, c], 0] + 1.0, uv[tri[f, c], 1]])
                    uv_faces[f, c] = len(uv) + len(extra) - 1
    if extra:
        uv = np.concatenate([uv, np.asarray(extra)])
    return uv, uv_faces


# ---------------------------------------------------------------- build


def build(out_dir: Path, settings: ShapeBuildSettings = ShapeBuildSettings()) -> dict:
    """Build ``out_dir/shape_model.{safetensors,json}``; returns the card."""
    from ..perception.store import write_card
    from .facemesh_topology import read_facemesh_topology, source_file

    t0 = time.perf_counter()
    s = settings
    topo = read_facemesh_topology()
    shapes = _facemesh_shapes(Path(out_dir))  # the perception nets built beside it, not the default dir
    mirror = _mirror_map(shapes)
    le, re_ = np.unique(topo.contours["left_eye"]), np.unique(topo.contours["right_eye"])
    scaled = [q * (IPD_MM / np.linalg.norm(q[le].mean(0) - q[re_].mean(0))) for q in shapes]
    # shapes[1::2] come from mirrored photos, un-mirrored: their landmark i sits at the place of mirror[i].
    # Re-indexed, they are the same people seen through FaceMesh twice: more samples of the mean.
    scaled = [q if i % 2 == 0 else q[mirror] for i, q in enumerate(scaled)]
    face = np.mean(scaled, axis=0)
    face = 0.5 * (face + _mirror_points(face, mirror))
    face = np.round(face, 2)
    face_tri = _symmetrise_topology(topo.triangles, mirror, face[:, 0])
    oval = _loop(topo.contours["face_oval"])
    head_pts, head_tri = _complete_head(face, oval, np.concatenate([le, re_]), s)
    coarse = np.concatenate([face, head_pts])
    tri = np.concatenate([face_tri, head_tri])
    # orientation: outward normals (positive signed volume of the closed-up head)
    vol = np.einsum("ij,ij->i", coarse[tri[:, 0]], np.cross(coarse[tri[:, 1]], coarse[tri[:, 2]])).sum()
    if vol < 0:
        tri = tri[:, [0, 2, 1]]
    # refinement
    import scipy.sparse as sp

    S = sp.identity(len(coarse), format="csr")
    fine_tri, n = tri, len(coarse)
    for _ in range(s.subdivisions):
        step, fine_tri = _subdivide(fine_tri, n, pinned=0)
        S = step @ S
        n = S.shape[0]
    # Loop smoothing pulls each landmark toward its neighbours; move the coarse landmark controls so
    # that the smooth surface passes through the FaceMesh mean (fixed-point iteration; S's landmark
    # rows weigh their own control most, so it converges).
    held = {"all": np.arange(468), "oval": oval, "none": np.zeros(0, np.int64)}[s.interpolate_landmarks]
    S_l = S[held]
    for _ in range(60 if len(held) else 0):
        coarse[held] += face[held] - S_l @ coarse
    residual = float(np.abs(S_l @ coarse - face[held]).max()) if len(held) else 0.0
    if residual > 0.01:
        raise ModelBuildError(f"landmark interpolation did not converge ({residual:.3g} mm)")
    mean = S @ coarse
    # smoothing moved the eye contours a little: rescale so the final mean's IPD is exactly 63 mm
    coarse *= IPD_MM / np.linalg.norm(mean[le].mean(0) - mean[re_].mean(0))
    mean = S @ coarse
    # mirror map on every vertex, from the exactly symmetric mean
    from scipy.spatial import cKDTree

    dist, full_mirror = cKDTree(mean).query(mean * [-1.0, 1.0, 1.0])
    if dist.max() > 1e-6 or not np.array_equal(full_mirror[full_mirror], np.arange(n)):
        raise ModelBuildError(f"the mean head is not mirror-symmetric (max {dist.max():.3g} mm)")
    # A neutral mean: both source photos smile with parted lips. Close the lips to a 0.5 mm slit with
    # the model's own mouthClose field (symmetric, local to the lips), before anything is measured on it.
    from .expressions import build_expressions, face_parts

    parts = face_parts(mean, topo.contours)
    close = build_expressions(mean, fine_tri, parts, ("mouthClose",))[0][:, :, 0]
    gap = float(mean[parts.lip_upper_inner, 1].mean() - mean[parts.lip_lower_inner, 1].mean())
    if gap > 0.5:
        mean = mean + close * ((gap - 0.5) / (gap + 2.0))
    # identity basis
    basis, eig, lam = _identity_basis(coarse, S, s)
    total = float(lam.sum())
    k = s.components
    uv, uv_faces = _cylindrical_uvs(mean, fine_tri, float(mean[:, 2].min() + (mean[:, 2].max() - mean[:, 2].min()) / 2))
    # expressions, correspondences, regions
    from ..perception.facemesh import IBUG68_FROM_FACEMESH
    from .regions import REGIONS, uv_region_map, vertex_regions

    expr, expr_scale = build_expressions(mean, fine_tri, face_parts(mean, topo.contours), topo.blendshape_names)
    face_weight = np.asarray(S[:, :468].sum(axis=1)).reshape(-1)
    labels = vertex_regions(mean, face_weight > 0.5, topo.contours)
    region_uv = uv_region_map(labels, fine_tri, uv, uv_faces)
    align5 = IBUG68_FROM_FACEMESH[[36, 39, 42, 45, 33]]  # dlib's 5 points: eye corners, nose base

    tensors = {
        "mean": mean.astype(np.float32),
        "triangles": fine_tri.astype(np.int32),
        "identity_basis": basis.reshape(n, 3, k).astype(np.float32),
        "identity_eigenvalues": eig.astype(np.float32),
        "mirror": full_mirror.astype(np.int32),
        "uv": uv.astype(np.float32),
        "uv_faces": uv_faces.astype(np.int32),
        "expression_basis": expr.astype(np.float32),
        "expression_scale": expr_scale.astype(np.float32),
        "landmarks": np.arange(468, dtype=np.int32),
        "ibug68": IBUG68_FROM_FACEMESH.astype(np.int32),
        "align5": align5.astype(np.int32),
        "regions": labels,
        "region_uv": region_uv,
    }
    from safetensors.numpy import save

    from ..io.atomic import atomic_write_bytes

    # safetensors.numpy writes an array's buffer as if it were C-ordered: a Fortran-ordered one (as LAPACK
    # returns) would be stored transposed in memory order
    tensors = {name: np.ascontiguousarray(a) for name, a in tensors.items()}
    atomic_write_bytes(Path(out_dir) / f"{NAME}.safetensors", save(tensors))
    ipd = float(np.linalg.norm(mean[le].mean(0) - mean[re_].mean(0)))
    min_angle = _min_angle(mean, fine_tri)
    card = {
        "name": NAME,
        "kind": "gp-morphable-model",
        "source": source_file().describe(),
        "data": "FaceMesh 3D predictions on scikit-image's astronaut and matplotlib's Grace Hopper (and mirror images)",
        "settings": json.loads(json.dumps(s.__dict__)),
        "vertices": int(n),
        "triangles": int(len(fine_tri)),
        "landmarks": "vertex i is FaceMesh landmark i for i < 468",
        "expressions": {"names": list(topo.blendshape_names), "units": "mm at activation 1",
                        "zero_fields": [n for n, sc in zip(topo.blendshape_names, expr_scale) if sc < 0.01]},
        "regions": list(REGIONS),
        "holes": "eyes and mouth are open holes (3 boundary loops); the rest of the head is closed",
        "metrics": {
            "ipd_mm": round(ipd, 2),
            "variance_explained_10": round(float(lam[:10].sum() / total), 4),
            "variance_explained_80": round(float(lam[:80].sum() / total), 4),
            "variance_explained_k": round(float(lam[:k].sum() / total), 4),
            "min_angle_deg": round(float(min_angle.min()), 2),
            "min_angle_p1_deg": round(float(np.percentile(min_angle, 1)), 2),
            "min_angle_median_deg": round(float(np.median(min_angle)), 2),
            "head_breadth_mm": round(float(np.ptp(mean[:, 0])), 1),
            "head_height_menton_to_vertex_mm": round(float(mean[:, 1].max() - mean[152, 1]), 1),
            "neck_below_chin_mm": round(float(mean[152, 1] - mean[:, 1].min()), 1),
            "face_height_nasion_menton_mm": round(float(mean[168, 1] - mean[152, 1]), 1),
            "forehead_top_to_menton_mm": round(float(mean[10, 1] - mean[152, 1]), 1),
        },
        "command": "fitme models build --only shape_model",
        "build_seconds": round(time.perf_counter() - t0, 2),
    }
    write_card(Path(out_dir) / f"{NAME}.json", card)
    return card
