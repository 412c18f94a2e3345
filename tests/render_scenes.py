"""Small meshes shared by the renderer tests (and the stability benchmark)."""

from __future__ import annotations

import torch


def bump_mesh(n=6, size=60.0, height=15.0, dtype=torch.float64):
    """An n x n vertex grid in the world x-y plane with a Gaussian bump toward +z (the camera), outward
    (counter-clockwise seen from +z) triangles, UVs u = x, v = y, and the shape model's normals and
    tangents. Returns vertices (1, V, 3), normals, tangents (1, V, 4), faces, uv (V, 2) float32, uv_faces."""
    from fitme_cli.shape.model import vertex_normals, vertex_tangents

    t = torch.linspace(-size / 2, size / 2, n, dtype=dtype)
    y, x = torch.meshgrid(t, t, indexing="ij")
    z = height * torch.exp(-(x**2 + y**2) / (2 * (size / 4) ** 2))
    verts = torch.stack([x, y, z], -1).reshape(1, -1, 3)
    idx = torch.arange(n * n).view(n, n)
    a, b, c, d = idx[:-1, :-1].reshape(-1), idx[:-1, 1:].reshape(-1), idx[1:, 1:].reshape(-1), idx[1:, :-1].reshape(-1)
    faces = torch.cat([torch.stack([a, b, c], 1), torch.stack([a, c, d], 1)])
    uv = ((verts[0, :, :2] + size / 2) / size).float()
    normals = vertex_normals(verts, faces)
    tangents = vertex_tangents(verts, faces, uv.to(dtype), faces, normals)
    return verts, normals, tangents, faces, uv, faces.clone()
