"""What ``fitme export`` and ``fitme render`` read from an avatar directory: the identity, the fitted
expressions, lights and effects, and the reflectance maps (maps/avatar_*.exr, docs/avatar_format.md).

The maps are read from the EXR files the fit wrote (half-float, linear, normals as n * 0.5 + 0.5):
they are exactly the maps of the tuned generator, and reading them needs no model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import AvatarInvalid, FitmeError
from .maps import SourceMaps

__all__ = ["AvatarSource", "load_source"]


@dataclass(frozen=True, eq=False)
class AvatarSource:
    """path: the avatar directory; p_s: (K,) identity coefficients; p_e: (P, E) fitted expression per
    photo; photo_names: (P,); lights: the fitted ``render.Lights`` (batch P, world frame); effects: the
    effects the fit chose; maps: the reflectance maps at the generator's resolution; fitted_vertices:
    (P, V, 3) float32 mm or None, the fitted meshes, for ``fitting.avatar.check_shape_model``."""

    path: Path
    p_s: np.ndarray
    p_e: np.ndarray
    photo_names: list[str]
    lights: object
    effects: object
    maps: SourceMaps
    fitted_vertices: np.ndarray | None


def load_source(avatar_dir: Path) -> AvatarSource:
    """Read and check an avatar directory; AvatarInvalid names what is missing or wrong."""
    from ..fitting.avatar import load_avatar
    from ..io.maps import read_map

    avatar_dir = Path(avatar_dir)
    av = load_avatar(avatar_dir)  # AvatarInvalid for a missing directory, avatar.json or params
    arrays = {}
    for name in ("albedo", "specular", "normals"):
        path = avatar_dir / "maps" / f"avatar_{name}.exr"
        if not path.is_file():
            raise AvatarInvalid(f"maps/{path.name} is missing", avatar_dir)
        try:
            arrays[name] = read_map(path).linear
        except FitmeError as e:
            raise AvatarInvalid(f"maps/{path.name} is unreadable: {e.message}", avatar_dir) from None
    shapes = {k: v.shape for k, v in arrays.items()}
    r = arrays["albedo"].shape[0]
    if any(s != (r, r, 3) for s in shapes.values()):
        raise AvatarInvalid(f"maps must be square RGB of one size, got {shapes}", avatar_dir)
    normals = arrays["normals"] * 2.0 - 1.0
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-6)
    maps = SourceMaps(np.clip(arrays["albedo"], 0, 1), np.clip(arrays["specular"][..., 0], 0, 1), normals.astype(np.float32))
    inv = av.inversion
    p_s = inv.p_s.detach().cpu().numpy().reshape(-1)
    p_e = inv.p_e.detach().cpu().numpy()
    if not (np.isfinite(p_s).all() and np.isfinite(p_e).all()):
        raise AvatarInvalid("params.safetensors holds non-finite shape or expression coefficients", avatar_dir)
    return AvatarSource(avatar_dir, p_s.astype(np.float64), p_e.astype(np.float64), [r_.name for r_ in av.records],
                        inv.lights, inv.effects, maps,
                        None if av.fitted_vertices is None else av.fitted_vertices.numpy())
