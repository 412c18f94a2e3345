"""The export mesh: the fitted head with its openings closed, split at UV seams, with normals,
glTF/MikkTSpace-convention tangents and the 52 ARKit expressions as morph-target deltas.

Two levels of vertices:

- *position* vertices (the shape model's V, plus one centre vertex per closed opening): what the
  renderer and the normals/tangents are computed on, so that shading is continuous across UV seams;
- *export* vertices (N): one per distinct (position, UV) pair, as every real-time format needs, since a
  vertex there has exactly one UV. The shape model's cylindrical UVs have one seam, at the back of the
  head, where triangles that cross it use u + 1 (samplers wrap u: glTF's default REPEAT).

The shape model's mesh has three openings (the eyes and the mouth). An exported head with holes there
shows the inside of the back of the head through them, so each is closed by a fan to a centre vertex
set back into the head (``MeshSettings.cap_depth_mm``). The centre is the mean of its rim plus a fixed
offset, a linear function of the rim, so it follows every identity and expression exactly, and its UV
is the mean of the rim's UVs: the texels the maps hold inside the eye and lip openings.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = ["MeshSettings", "HeadTopology", "head_topology", "head_vertices", "Geometry", "ExportMesh",
           "build_export_mesh", "geometry", "MM_PER_M"]

MM_PER_M = 1000.0


@dataclass(frozen=True)
class MeshSettings:
    """cap_depth_mm: how far behind its rim each opening's centre vertex sits, for the openings found
    in size order (the mouth is the longest rim, then the two eyes); a deeper cap reads as a cavity.
    target_epsilon_m: morph-target deltas smaller than this (metres) are stored as exact zeros, so
    targets can be written as sparse accessors."""

    cap_depth_mm: tuple[float, ...] = (8.0, 2.0, 2.0)
    target_epsilon_m: float = 1e-7

    def __post_init__(self) -> None:
        if not self.cap_depth_mm or any(not (0.0 <= d <= 50.0) for d in self.cap_depth_mm):
            raise ValueError(f"cap_depth_mm must be one or more depths in [0, 50] mm, got {self.cap_depth_mm!r}")
        if not 0.0 <= self.target_epsilon_m < 1e-3:
            raise ValueError(f"target_epsilon_m must be in [0, 1e-3), got {self.target_epsilon_m!r}")


@dataclass(frozen=True, eq=False)
class HeadTopology:
    """The shape model's mesh with its openings closed (all arrays numpy).

    triangles: (F, 3) int64 position-vertex indices, outward (counter-clockwise seen from outside);
    uv: (T, 2) float64 texture coordinates, OpenGL convention (v = 1 at the top row of a map; u may
    exceed 1 across the back seam); uv_faces: (F, 3) int64 indices into ``uv``; n_model: V, the shape
    model's vertices; loops: one (L_i,) int64 array of rim vertices per closed opening; offsets: (C, 3)
    mm, each centre vertex minus the mean of its rim (set on the mean shape)."""

    triangles: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    n_model: int
    loops: tuple[np.ndarray, ...]
    offsets: np.ndarray

    @property
    def n_vertices(self) -> int:
        """Position vertices: the model's plus one centre per closed opening."""
        return self.n_model + len(self.loops)

    def extend(self, x: torch.Tensor | np.ndarray, offset: bool) -> torch.Tensor | np.ndarray:
        """Per-vertex rows (..., V, C) -> (..., V + caps, C): each centre the mean of its rim's rows, plus
        the centre's offset when ``offset`` (positions; not for deltas or bases, which stay linear)."""
        if x.shape[-2] != self.n_model:
            raise ValueError(f"expected {self.n_model} rows on axis -2, got shape {tuple(x.shape)}")
        is_torch = isinstance(x, torch.Tensor)
        rows = []
        for i, loop in enumerate(self.loops):
            idx = torch.as_tensor(loop, device=x.device) if is_torch else loop
            c = x[..., idx, :].mean(-2, keepdim=True) if is_torch else x[..., idx, :].mean(-2, keepdims=True)
            if offset:
                off = self.offsets[i]
                c = c + (torch.as_tensor(off, dtype=x.dtype, device=x.device) if is_torch else off.astype(x.dtype))
            rows.append(c)
        return torch.cat([x, *rows], -2) if is_torch else np.concatenate([x, *rows], -2)


def _boundary_loops(tri: np.ndarray, uvf: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Rims of the mesh's openings: per loop (vertices in walking order, their uv indices, the directed
    boundary edges (a, b) as they appear in their triangles)."""
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    euv = np.concatenate([uvf[:, [0, 1]], uvf[:, [1, 2]], uvf[:, [2, 0]]])
    key = np.sort(e, 1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = counts[inv.ravel()] == 1
    nxt = {int(a): (int(b), int(ua)) for (a, b), (ua, _) in zip(e[boundary], euv[boundary])}
    if len(nxt) != int(boundary.sum()):
        raise ValueError("the mesh has a pinched boundary (a vertex on two openings); cannot close it")
    loops, seen = [], set()
    for start in sorted(nxt):
        if start in seen:
            continue
        verts, uvs, v = [], [], start
        while v not in seen:
            seen.add(v)
            b, uv_idx = nxt[v]
            verts.append(v)
            uvs.append(uv_idx)
            v = b
        if v != start:
            raise ValueError("an open boundary that does not close into a loop")
        verts = np.asarray(verts, np.int64)
        loops.append((verts, np.asarray(uvs, np.int64), np.stack([verts, np.roll(verts, -1)], 1)))
    return sorted(loops, key=lambda lp: -len(lp[0]))


def head_topology(shape_model, settings: MeshSettings = MeshSettings()) -> HeadTopology:
    """Close every opening of the shape model's mesh with a fan (see the module docstring)."""
    from ..shape.model import vertex_normals

    tri = shape_model.triangles.cpu().numpy().astype(np.int64)
    uvf = shape_model.uv_faces.cpu().numpy().astype(np.int64)
    uv = shape_model.uv.cpu().numpy().astype(np.float64)
    mean = shape_model.mean.cpu().double()
    n_model = int(mean.shape[0])
    normals = vertex_normals(mean[None], torch.as_tensor(tri))[0].numpy()
    loops = _boundary_loops(tri, uvf)
    new_tri, new_uvf, new_uv, offsets = [], [], [], []
    for i, (verts, uv_idx, edges) in enumerate(loops):
        depth = settings.cap_depth_mm[min(i, len(settings.cap_depth_mm) - 1)]
        inward = -normals[verts].mean(0)
        inward /= max(np.linalg.norm(inward), 1e-12)
        offsets.append(inward * depth)
        centre, centre_uv = n_model + i, len(uv) + i
        new_uv.append(uv[uv_idx].mean(0))
        # the rim edge a -> b runs one way in its triangle, so the cap's triangle runs b -> a: consistent winding
        for (a, b), ua, ub in zip(edges, uv_idx, np.roll(uv_idx, -1)):
            new_tri.append([b, a, centre])
            new_uvf.append([ub, ua, centre_uv])
    if new_tri:
        tri = np.concatenate([tri, np.asarray(new_tri, np.int64)])
        uvf = np.concatenate([uvf, np.asarray(new_uvf, np.int64)])
        uv = np.concatenate([uv, np.asarray(new_uv)])
    return HeadTopology(tri, uv, uvf, n_model, tuple(lp[0] for lp in loops),
                        np.asarray(offsets, np.float64).reshape(-1, 3))


def head_vertices(shape_model, topo: HeadTopology, p_s: torch.Tensor, p_e: torch.Tensor) -> torch.Tensor:
    """(B, K), (B, E) -> (B, V + caps, 3) float64 mm in the model frame, the caps' centres included.
    Computed from float64 copies of the model's buffers (the model itself is not converted)."""
    p_s, p_e = torch.as_tensor(p_s).double().cpu(), torch.as_tensor(p_e).double().cpu()
    if p_s.ndim != 2 or p_s.shape[1] != shape_model.n_identity or p_e.ndim != 2 or p_e.shape[1] != shape_model.n_expressions:
        raise ValueError(f"expected p_s (B, {shape_model.n_identity}) and p_e (B, {shape_model.n_expressions}), "
                         f"got {tuple(p_s.shape)} and {tuple(p_e.shape)}")
    v = (shape_model.mean.detach().cpu().double()
         + torch.einsum("vck,bk->bvc", shape_model.identity_basis.detach().cpu().double(), p_s)
         + torch.einsum("vce,be->bvc", shape_model.expression_basis.detach().cpu().double(), p_e))
    return topo.extend(v, offset=True)


@dataclass(frozen=True, eq=False)
class Geometry:
    """Per export vertex, float32: positions (N, 3) metres; normals (N, 3) unit; tangents (N, 4): xyz
    unit along +u, w = +-1 with bitangent = w * (normal x tangent) along +v (glTF's convention)."""

    positions: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray


@dataclass(frozen=True, eq=False)
class ExportMesh:
    """The head ready to write. Frame: the shape model's world frame in metres (x to the subject's left,
    y up, z out of the face: glTF's +Y up, +Z forward).

    faces: (F, 3) int64 export-vertex indices, counter-clockwise from outside; uv: (N, 2) float32,
    OpenGL convention (v up; glTF stores t = 1 - v); position_index: (N,) the position vertex of each
    export vertex; neutral: the neutral expression; posed: with ``weights`` applied (recomputed, not
    blended); target_names: the expression names (ARKit); target_positions, target_normals: (E, N, 3)
    float32 deltas for weight 1 (exact zeros below ``MeshSettings.target_epsilon_m``); weights: (E,)
    the expression the export shows by default (zeros: neutral)."""

    faces: np.ndarray
    uv: np.ndarray
    position_index: np.ndarray
    neutral: Geometry
    posed: Geometry
    target_names: list[str]
    target_positions: np.ndarray
    target_normals: np.ndarray
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    @property
    def n_vertices(self) -> int:
        return int(self.uv.shape[0])


def geometry(topo: HeadTopology, vertices_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Position-vertex geometry of a batch: (B, V + caps, 3) mm -> vertices, unit normals (B, ., 3),
    tangents (B, ., 4) (the renderer's convention, ``shape.model.vertex_tangents``)."""
    from ..shape.model import vertex_normals, vertex_tangents

    faces = torch.as_tensor(topo.triangles, device=vertices_mm.device)
    n = vertex_normals(vertices_mm, faces)
    t = vertex_tangents(vertices_mm, faces, torch.as_tensor(topo.uv, dtype=vertices_mm.dtype, device=vertices_mm.device),
                        torch.as_tensor(topo.uv_faces, device=vertices_mm.device), n)
    return vertices_mm, n, _repair_tangents(t, n)


def _repair_tangents(t: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """A vertex whose triangles all have degenerate UVs gets a zero tangent; give it any unit vector
    perpendicular to its normal (glTF requires unit tangents), keeping w."""
    xyz, w = t[..., :3], t[..., 3:]
    bad = xyz.norm(dim=-1, keepdim=True) < 0.5
    if not bool(bad.any()):
        return t
    helper = torch.where(n[..., 1:2].abs() < 0.9, torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype), torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype))
    alt = torch.nn.functional.normalize(torch.cross(helper, n, dim=-1), dim=-1, eps=1e-12)
    return torch.cat([torch.where(bad, alt, xyz), w], -1)


def _split(topo: HeadTopology) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One export vertex per distinct (position, uv) pair: (position_index (N,), uv_index (N,), faces (F, 3)).
    UVs are compared by value: the shape model's seam gives a position one u + 1 copy per triangle
    corner across the seam, and those identical copies must not split the vertex further."""
    _, first, canon = np.unique(topo.uv, axis=0, return_index=True, return_inverse=True)
    uv_canon = first[canon.ravel()]  # each uv index -> the first index with the same coordinates
    pairs = np.stack([topo.triangles.ravel(), uv_canon[topo.uv_faces.ravel()]], 1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], uniq[:, 1], inv.reshape(-1, 3).astype(np.int64)


def build_export_mesh(shape_model, p_s: torch.Tensor, weights: np.ndarray | None = None,
                      settings: MeshSettings = MeshSettings(), topo: HeadTopology | None = None) -> ExportMesh:
    """The export mesh of identity ``p_s`` (K,) or (1, K); ``weights`` (E,): the expression to pose (None:
    neutral). Deltas are for the neutral identity shape; normals and tangents are recomputed for the pose."""
    E = shape_model.n_expressions
    p_s = torch.as_tensor(p_s).reshape(1, -1).double().cpu()
    if p_s.shape[1] != shape_model.n_identity:
        raise ValueError(f"p_s: expected {shape_model.n_identity} identity coefficients, got {p_s.shape[1]}")
    w = np.zeros(E, np.float64) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    if w.shape != (E,) or not np.isfinite(w).all():
        raise ValueError(f"weights: expected {E} finite expression weights, got shape {w.shape}")
    topo = topo or head_topology(shape_model, settings)
    base = head_vertices(shape_model, topo, p_s, torch.zeros(1, E, dtype=torch.float64))  # (1, P, 3) mm
    expr = shape_model.expression_basis.detach().cpu().double()
    basis = topo.extend(expr.permute(2, 0, 1), offset=False)  # (E, P, 3) mm per unit weight
    posed = base + torch.einsum("epc,e->pc", basis, torch.as_tensor(w))[None] if w.any() else base
    _, n0, t0 = geometry(topo, base)
    _, np_, tp = geometry(topo, posed) if w.any() else (None, n0, t0)
    _, n_targets, _ = geometry(topo, base + basis)  # each expression at weight 1
    pos_idx, uv_idx, faces = _split(topo)

    def per_export(x: torch.Tensor) -> np.ndarray:
        return x[..., torch.as_tensor(pos_idx), :].numpy()

    def geo(v, n, t) -> Geometry:
        return Geometry((per_export(v)[0] / MM_PER_M).astype(np.float32), per_export(n)[0].astype(np.float32),
                        per_export(t)[0].astype(np.float32))

    d_pos = per_export(basis) / MM_PER_M
    d_nrm = per_export(n_targets - n0)
    eps = settings.target_epsilon_m
    moved = np.linalg.norm(d_pos, axis=-1, keepdims=True) > eps
    # a vertex that does not move keeps its normal; tiny normal changes there are round-off
    d_pos = np.where(moved, d_pos, 0.0).astype(np.float32)
    d_nrm = np.where(moved & (np.abs(d_nrm) > 1e-6).any(-1, keepdims=True), d_nrm, 0.0).astype(np.float32)
    return ExportMesh(faces, topo.uv[uv_idx].astype(np.float32), pos_idx, geo(base, n0, t0), geo(posed, np_, tp),
                      list(shape_model.expression_names), d_pos, d_nrm, w.astype(np.float32))
