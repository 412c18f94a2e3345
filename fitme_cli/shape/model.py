"""The shape model S(p_s, p_e) = m + U_s p_s + U_e p_e as torch buffers: batched and differentiable.

Units and frame: millimetres; model axes x to the subject's left, y up, z out of the face (toward a
viewer in front). U_s is orthonormal over all 3V coordinates with eigenvalues lambda (mm^2), so
p_s ~ N(0, diag(lambda)) is the identity prior and ||p_s||^2_{Sigma_s^-1} = sum p_s^2 / lambda.
Expression coefficients p_e are blendshape activations (0 = neutral, 1 = full), with prior scales sigma_e.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..errors import ModelMissing

__all__ = ["ShapeOutput", "ShapeModel", "vertex_normals", "vertex_tangents", "load_shape_model"]


@dataclass(frozen=True)
class ShapeOutput:
    vertices: torch.Tensor  # (B, V, 3) mm, model frame
    normals: torch.Tensor  # (B, V, 3) unit, outward (area-weighted face normals)
    tangents: torch.Tensor  # (B, V, 4): unit tangent along +u of the UV layout, w = handedness (+-1)


def _accumulate(per_face: torch.Tensor, faces: torch.Tensor, like: torch.Tensor, incidence=None) -> torch.Tensor:
    """Sum per-face values (B, F, C) onto each face's three vertices -> (B, V, C). With ``incidence``
    (``ops.sparse.incidence``: one CSR product, ~10x faster on the CPU) or by index_add (the reference)."""
    if incidence is None:
        out = torch.zeros(*like.shape[:2], per_face.shape[-1], dtype=per_face.dtype, device=per_face.device)
        for i in range(3):
            out = out.index_add(1, faces[:, i], per_face)
        return out
    from ..ops.sparse import sparse_apply

    b, f, c = per_face.shape
    x = per_face.permute(1, 0, 2).reshape(f, b * c).repeat(3, 1)  # (3F, B*C): one row per corner
    a, at = incidence
    return sparse_apply(a, at, x).view(-1, b, c).permute(1, 0, 2)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor, incidence=None) -> torch.Tensor:
    """(B, V, 3), (F, 3) long -> (B, V, 3) unit area-weighted vertex normals."""
    v0, v1, v2 = (vertices[:, faces[:, i]] for i in range(3))
    fn = torch.cross(v1 - v0, v2 - v0, dim=-1)  # length = 2 x area
    return torch.nn.functional.normalize(_accumulate(fn, faces, vertices, incidence), dim=-1, eps=1e-12)


def vertex_tangents(vertices: torch.Tensor, faces: torch.Tensor, uv: torch.Tensor, uv_faces: torch.Tensor,
                    normals: torch.Tensor, incidence=None) -> torch.Tensor:
    """Per-vertex tangent frame for tangent-space normal maps (the MikkTSpace idea, simplified):
    per-face dP/du accumulated on vertices, orthogonalised against the normal. Returns (B, V, 4) with
    w = +1 when (N x T) points along +v, else -1 (glTF's convention for the bitangent)."""
    p0, p1, p2 = (vertices[:, faces[:, i]] for i in range(3))
    t0, t1, t2 = (uv[uv_faces[:, i]] for i in range(3))
    e1, e2 = p1 - p0, p2 - p0
    d1, d2 = t1 - t0, t2 - t0
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    r = torch.where(det.abs() > 1e-12, 1.0 / det, torch.zeros_like(det))[None, :, None]
    tan = (e1 * d2[None, :, 1:2] - e2 * d1[None, :, 1:2]) * r
    bit = (e2 * d1[None, :, 0:1] - e1 * d2[None, :, 0:1]) * r
    acc = _accumulate(torch.cat([tan, bit], -1), faces, vertices, incidence)
    T, Bt = acc[..., :3], acc[..., 3:]
    T = T - normals * (normals * T).sum(-1, keepdim=True)
    T = torch.nn.functional.normalize(T, dim=-1, eps=1e-12)
    w = torch.where((torch.cross(normals, T, dim=-1) * Bt).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    return torch.cat([T, w.to(T.dtype)], dim=-1)


class ShapeModel(nn.Module):
    """``forward(p_s (B, K), p_e (B, E))`` -> ShapeOutput. All data are buffers (``.to``, ``.double()``)."""

    def __init__(self, tensors: dict[str, np.ndarray], expression_names: list[str]):
        super().__init__()
        for name, value in tensors.items():
            t = torch.from_numpy(np.ascontiguousarray(value))
            self.register_buffer(name, t.long() if value.dtype.kind in "iu" else t.float())
        self.expression_names = list(expression_names)
        if self.expression_basis.shape[2] != len(self.expression_names):
            raise ValueError("expression basis and names disagree")

    @property
    def n_identity(self) -> int:
        return int(self.identity_basis.shape[2])

    @property
    def n_expressions(self) -> int:
        return int(self.expression_basis.shape[2])

    def _check(self, p: torch.Tensor, n: int, what: str) -> None:
        if p.ndim != 2 or p.shape[1] != n:
            raise ValueError(f"expected {what} of shape (B, {n}), got {tuple(p.shape)}")

    def vertices(self, p_s: torch.Tensor, p_e: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) mm: m + U_s p_s + U_e p_e."""
        self._check(p_s, self.n_identity, "p_s")
        self._check(p_e, self.n_expressions, "p_e")
        if p_s.shape[0] != p_e.shape[0]:
            raise ValueError(f"p_s and p_e batch sizes differ: {p_s.shape[0]} vs {p_e.shape[0]}")
        return (self.mean + torch.einsum("vck,bk->bvc", self.identity_basis, p_s)
                + torch.einsum("vce,be->bvc", self.expression_basis, p_e))

    def _incidence(self, v: torch.Tensor):
        key = (v.dtype, v.device)
        if not hasattr(self, "_incidence_cache"):
            self._incidence_cache = {}
        if key not in self._incidence_cache:
            from ..ops.sparse import incidence

            a, at = incidence(self.triangles.cpu(), self.mean.shape[0])
            self._incidence_cache[key] = (a.to(device=v.device, dtype=v.dtype), at.to(device=v.device, dtype=v.dtype))
        return self._incidence_cache[key]

    def forward(self, p_s: torch.Tensor, p_e: torch.Tensor) -> ShapeOutput:
        v = self.vertices(p_s, p_e)
        inc = self._incidence(v)
        n = vertex_normals(v, self.triangles, inc)
        return ShapeOutput(v, n, vertex_tangents(v, self.triangles, self.uv, self.uv_faces, n, inc))

    def identity_prior(self, p_s: torch.Tensor) -> torch.Tensor:
        """(B,) ||p_s||^2 in the metric Sigma_s^-1 (a squared Mahalanobis distance, unitless)."""
        self._check(p_s, self.n_identity, "p_s")
        return (p_s**2 / self.identity_eigenvalues).sum(-1)

    def expression_prior(self, p_e: torch.Tensor) -> torch.Tensor:
        """(B,) sum (p_e / sigma_e)^2."""
        self._check(p_e, self.n_expressions, "p_e")
        return ((p_e / self.expression_scale) ** 2).sum(-1)

    def sample_identity(self, n: int, generator: torch.Generator | None = None, sigma: float = 1.0) -> torch.Tensor:
        """(n, K) draws of p_s ~ N(0, sigma^2 diag(lambda))."""
        z = torch.randn(n, self.n_identity, generator=generator, dtype=self.mean.dtype, device=self.mean.device)
        return z * sigma * self.identity_eigenvalues.sqrt()

    def zeros(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        kw = {"dtype": self.mean.dtype, "device": self.mean.device}
        return torch.zeros(batch, self.n_identity, **kw), torch.zeros(batch, self.n_expressions, **kw)


def load_shape_model(models_dir: Path) -> ShapeModel:
    """The shape model built by ``fitme models build`` (ModelMissing if it is not there)."""
    import json

    from safetensors.numpy import load_file

    path = Path(models_dir) / "shape_model.safetensors"
    card_path = Path(models_dir) / "shape_model.json"
    if not path.is_file() or not card_path.is_file():
        raise ModelMissing("shape model is missing; run: fitme models build", path)
    card = json.loads(card_path.read_text())
    return ShapeModel(load_file(str(path)), card["expressions"]["names"]).eval()
