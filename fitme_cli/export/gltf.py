"""glTF 2.0 writer (JSON + .bin, and binary GLB), by hand so every field and extension is ours.

One node, one mesh, one triangle primitive: POSITION (metres), NORMAL, TANGENT (xyz along +u, w = the
bitangent's sign: bitangent = w * normal x tangent, along +v), TEXCOORD_0 (t = 1 - v: glTF's origin is
the image's top-left), uint16/uint32 indices. The 52 ARKit expressions are morph targets (POSITION and
NORMAL deltas) named in ``mesh.extras.targetNames``; each is a sparse accessor holding only the
vertices that move (an expression that moves nothing, e.g. eyeLook* on a head without eyeballs, is an
all-zero accessor without data). ``mesh.weights`` is the default expression (zeros, or the fitted one).

Material: metallic-roughness with metallic 0, baseColorTexture = the diffuse albedo (sRGB PNG),
normalTexture = the tangent-space normals (16-bit PNG, OpenGL +Y, as glTF specifies),
KHR_materials_specular = the specular albedo as ``specularColorTexture`` (grey, sRGB PNG) times
``specularColorFactor`` (``material.py`` has the mapping). The sampler repeats u
(the head's UVs cross u = 1 at the back seam) and clamps v.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from .material import Material
from .mesh import ExportMesh

__all__ = ["gltf_document", "glb_bytes", "TEXTURE_SLOTS"]

TEXTURE_SLOTS = ("albedo", "normals", "specular")  # image/texture index order

_FLOAT, _UINT16, _UINT32 = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _REPEAT, _CLAMP = 9729, 9987, 10497, 33071


class _Bin:
    """The binary buffer and its views, each view 4-byte aligned (accessor alignment rules)."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.length = 0
        self.views: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        v = {"buffer": 0, "byteOffset": self.length, "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        self.chunks.append(data)
        pad = (-len(data)) % 4
        if pad:
            self.chunks.append(b"\0" * pad)
        self.length += len(data) + pad
        self.views.append(v)
        return len(self.views) - 1

    def bytes(self) -> bytes:
        return b"".join(self.chunks)


def _f32(x) -> list[float]:
    return [float(v) for v in np.asarray(x, np.float32).ravel()]


def _vec_type(n: int) -> str:
    return {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}[n]


def _dense(buf: _Bin, accessors: list, arr: np.ndarray, minmax: bool = False) -> int:
    arr = np.ascontiguousarray(arr, np.float32)
    a = {"bufferView": buf.view(arr.tobytes(), _ARRAY_BUFFER), "componentType": _FLOAT, "count": int(arr.shape[0]),
         "type": _vec_type(arr.shape[1])}
    if minmax:
        a["min"], a["max"] = _f32(arr.min(0)), _f32(arr.max(0))
    accessors.append(a)
    return len(accessors) - 1


def _sparse(buf: _Bin, accessors: list, arr: np.ndarray, minmax: bool) -> int:
    """A morph-target accessor: zeros except the rows with a non-zero component (sparse)."""
    arr = np.ascontiguousarray(arr, np.float32)
    rows = np.nonzero((arr != 0).any(1))[0]
    a = {"componentType": _FLOAT, "count": int(arr.shape[0]), "type": _vec_type(arr.shape[1])}
    if minmax:  # over every row, the implicit zeros included
        a["min"], a["max"] = _f32(arr.min(0)), _f32(arr.max(0))
    if len(rows):
        itype, dt = (_UINT16, np.uint16) if arr.shape[0] < 65536 else (_UINT32, np.uint32)
        a["sparse"] = {"count": int(len(rows)),
                       "indices": {"bufferView": buf.view(rows.astype(dt).tobytes()), "componentType": itype},
                       "values": {"bufferView": buf.view(np.ascontiguousarray(arr[rows]).tobytes())}}
    accessors.append(a)
    return len(accessors) - 1


def gltf_document(mesh: ExportMesh, material: Material, images: dict[str, bytes] | None = None,
                  image_uris: dict[str, str] | None = None, buffer_uri: str | None = None,
                  extras: dict | None = None) -> tuple[dict, bytes]:
    """The glTF JSON and its binary buffer. Images: either PNG bytes per TEXTURE_SLOTS name (embedded
    in the buffer: GLB) or relative URIs (glTF with external files). ``buffer_uri``: the .bin's name for
    .gltf, None for GLB."""
    if (images is None) == (image_uris is None):
        raise ValueError("give either images (embedded) or image_uris (external), not both or neither")
    names = images if images is not None else image_uris
    missing = [k for k in TEXTURE_SLOTS if k not in names]
    if missing:
        raise ValueError(f"gltf_document: images for {', '.join(missing)} are missing")
    n = mesh.n_vertices
    if len(mesh.target_names) != len(mesh.target_positions) or mesh.target_positions.shape[1:] != (n, 3):
        raise ValueError(f"morph targets: {len(mesh.target_names)} names for targets of shape {mesh.target_positions.shape}")
    buf, acc = _Bin(), []
    g = mesh.neutral
    st = np.stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]], 1)
    attributes = {"POSITION": _dense(buf, acc, g.positions, minmax=True), "NORMAL": _dense(buf, acc, g.normals),
                  "TANGENT": _dense(buf, acc, g.tangents), "TEXCOORD_0": _dense(buf, acc, st)}
    itype, dt = (_UINT16, np.uint16) if n < 65536 else (_UINT32, np.uint32)
    faces = np.ascontiguousarray(mesh.faces.astype(dt))
    acc.append({"bufferView": buf.view(faces.tobytes(), _ELEMENT_ARRAY_BUFFER), "componentType": itype,
                "count": int(faces.size), "type": "SCALAR"})
    indices = len(acc) - 1
    targets = [{"POSITION": _sparse(buf, acc, dp, minmax=True), "NORMAL": _sparse(buf, acc, dn, minmax=False)}
               for dp, dn in zip(mesh.target_positions, mesh.target_normals)]
    weights = [float(w) for w in mesh.weights] if len(mesh.weights) else [0.0] * len(targets)
    if images is not None:
        gl_images = [{"bufferView": buf.view(images[k]), "mimeType": "image/png", "name": k} for k in TEXTURE_SLOTS]
    else:
        gl_images = [{"uri": image_uris[k], "mimeType": "image/png", "name": k} for k in TEXTURE_SLOTS]
    tex = {k: i for i, k in enumerate(TEXTURE_SLOTS)}
    k = material.specular_colour_factor
    doc = {
        "asset": {"version": "2.0", "generator": "fitme export", "extras": extras or {}},
        "extensionsUsed": ["KHR_materials_specular"],
        "scene": 0,
        "scenes": [{"name": "fitme", "nodes": [0]}],
        "nodes": [{"name": "head", "mesh": 0}],
        "meshes": [{"name": "head", "primitives": [{"attributes": attributes, "indices": indices, "material": 0,
                                                     "mode": 4, "targets": targets}],
                    "weights": weights, "extras": {"targetNames": list(mesh.target_names)}}],
        "materials": [{"name": material.name,
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": tex["albedo"]}, "metallicFactor": 0.0,
                                                "roughnessFactor": round(material.roughness, 6)},
                       "normalTexture": {"index": tex["normals"], "scale": 1.0},
                       "extensions": {"KHR_materials_specular": {"specularColorTexture": {"index": tex["specular"]},
                                                                 "specularColorFactor": [round(k, 6)] * 3}}}],
        "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR, "wrapS": _REPEAT, "wrapT": _CLAMP}],
        "textures": [{"sampler": 0, "source": i, "name": name} for i, name in enumerate(TEXTURE_SLOTS)],
        "images": gl_images,
        "accessors": acc,
        "bufferViews": buf.views,
        "buffers": [{"byteLength": buf.length} | ({"uri": buffer_uri} if buffer_uri else {})],
    }
    return doc, buf.bytes()


def glb_bytes(doc: dict, binary: bytes) -> bytes:
    """A GLB container: 12-byte header, the JSON chunk (space-padded) and the BIN chunk (zero-padded)."""
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * ((-len(js)) % 4)
    binary += b"\0" * ((-len(binary)) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(binary), 0x004E4942) + binary)
