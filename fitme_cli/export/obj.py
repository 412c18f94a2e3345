"""Wavefront OBJ + MTL writer.

OBJ has no tangents or morph targets: it holds one pose (the neutral or the fitted expression) with
positions in metres, UVs (v up, OBJ's convention) and the smooth normals; every export vertex has its
own v/vt/vn triple, so ``f a/a/a ...``. Consumers build their own tangent frames from the UVs
(MikkTSpace in Blender).

The MTL uses the classic Blinn-Phong fields (``map_Kd`` the diffuse albedo, ``map_Ks`` the specular
albedo, ``Ns`` the shininess) plus the normal map twice: ``norm`` (the PBR extension of MTL) and
``map_Bump -bm 1`` (what Blender's and most importers read as a tangent-space normal map).
"""

from __future__ import annotations

import io

import numpy as np

from .material import Material
from .mesh import ExportMesh, Geometry

__all__ = ["obj_text", "mtl_text"]


def obj_text(mesh: ExportMesh, geometry: Geometry, mtl_name: str, material: Material, comment: str) -> str:
    """The OBJ of ``geometry`` (``mesh.neutral`` or ``mesh.posed``), using material library ``mtl_name``."""
    out = io.StringIO()
    out.write(f"# {comment}\n# units: metres; frame: x to the subject's left, y up, z out of the face\n")
    out.write(f"mtllib {mtl_name}\no head\n")
    # %.7g keeps float32 positions (metres) to ~0.1 micrometre; UVs and normals to 1e-7
    np.savetxt(out, geometry.positions, fmt="v %.7g %.7g %.7g")
    np.savetxt(out, mesh.uv, fmt="vt %.7g %.7g")
    np.savetxt(out, geometry.normals, fmt="vn %.6f %.6f %.6f")
    out.write(f"usemtl {material.name}\ns 1\n")
    f = mesh.faces + 1
    np.savetxt(out, np.repeat(f, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    return out.getvalue()


def mtl_text(material: Material, maps: dict[str, str]) -> str:
    """The MTL for ``maps`` {albedo, specular, normals: file name relative to the MTL}."""
    return (f"# fitme export: Blinn-Phong skin; textures in the shape model's UV layout (u wraps)\n"
            f"newmtl {material.name}\n"
            "Ka 0 0 0\nKd 1 1 1\nKs 1 1 1\n"
            f"Ns {material.shininess:g}\n"
            "d 1\nillum 2\n"
            f"Pr {material.roughness:.4f}\nPm 0\n"
            f"map_Kd {maps['albedo']}\n"
            f"map_Ks {maps['specular']}\n"
            f"norm {maps['normals']}\n"
            f"map_Bump -bm 1 {maps['normals']}\n")
