"""``fitme export`` as one function: read the avatar, build the mesh and the maps, write the files.

Output layout (OUT is a directory; docs/export.md):

    head.glb                 glTF binary, textures embedded            (--format glb)
    head.gltf, head.bin      glTF JSON + buffer, textures as the PNGs   (--format gltf)
    head.obj, head.mtl       OBJ + MTL, textures as the PNGs            (--format obj)
    albedo.{exr,png}  specular.{exr,png}  normals.{exr,png}             (--maps; PNGs also when obj/gltf need them)
    export.json              what was written: settings, conventions, sizes, timings

Writing: every file goes to a hidden staging directory inside OUT first; only when all are complete are
they renamed into place (each rename atomic), so an interrupted export leaves no half-written file.
Existing files are replaced only with ``force``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import OutputNotWritable
from .maps import ExportMaps, MapSettings
from .material import Material
from .mesh import ExportMesh, MeshSettings

__all__ = ["FORMATS", "MAP_FORMATS", "EXPRESSIONS", "ExportSettings", "ExportResult", "planned_files",
           "check_output", "check_output_file", "export_avatar"]

FORMATS = ("glb", "gltf", "obj")
MAP_FORMATS = ("exr", "png")
EXPRESSIONS = ("neutral", "fitted")


@dataclass(frozen=True)
class ExportSettings:
    """formats: any of FORMATS; maps: any of MAP_FORMATS (standalone map files); resolution: map side;
    expression: "neutral", or "fitted" (the first photo's expression: baked into the OBJ, the default
    morph weights of the glTF); force: replace existing files."""

    formats: tuple[str, ...] = ("glb", "obj")
    maps: tuple[str, ...] = ("exr", "png")
    resolution: int = 1024
    expression: str = "neutral"
    force: bool = False
    mesh: MeshSettings = field(default_factory=MeshSettings)
    material: Material = field(default_factory=Material)

    def __post_init__(self) -> None:
        for name, got, allowed in (("formats", self.formats, FORMATS), ("maps", self.maps, MAP_FORMATS)):
            bad = [x for x in got if x not in allowed]
            if bad or (name == "formats" and not got) or len(set(got)) != len(got):
                raise ValueError(f"{name}: expected distinct values from {', '.join(allowed)}, got {', '.join(got) or 'none'}")
        if self.expression not in EXPRESSIONS:
            raise ValueError(f"expression must be one of {', '.join(EXPRESSIONS)}, got {self.expression!r}")
        MapSettings(self.resolution)  # the resolution's own check


@dataclass(frozen=True, eq=False)
class ExportResult:
    """files: name -> path written; sizes: name -> bytes; seconds: per stage (load, mesh, maps, write,
    total); mesh, maps: what was written (the arrays, for checks); expression: what the export shows."""

    out_dir: Path
    files: dict[str, Path]
    sizes: dict[str, int]
    seconds: dict[str, float]
    mesh: ExportMesh
    maps: ExportMaps
    expression: str


def planned_files(settings: ExportSettings) -> list[str]:
    """The file names an export with ``settings`` writes into OUT."""
    names = []
    pngs = "png" in settings.maps or "obj" in settings.formats or "gltf" in settings.formats
    for kind in ("albedo", "specular", "normals"):
        if "exr" in settings.maps:
            names.append(f"{kind}.exr")
        if pngs:
            names.append(f"{kind}.png")
    per_format = {"glb": ["head.glb"], "gltf": ["head.gltf", "head.bin"], "obj": ["head.obj", "head.mtl"]}
    for fmt in settings.formats:
        names += per_format[fmt]
    return names


def check_output(out_dir: Path, avatar_dir: Path, names: list[str], force: bool) -> None:
    """Refuse before any work: OUT not a directory, OUT inside (or equal to) the avatar directory, files
    that exist (without ``force``), or a place that cannot be written."""
    out_dir, avatar_dir = Path(out_dir), Path(avatar_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputNotWritable("the output path exists and is not a directory", out_dir)
    out_r, av_r = out_dir.resolve(), avatar_dir.resolve()
    if out_r == av_r or av_r in out_r.parents:
        raise OutputNotWritable(f"the output is inside the avatar directory {avatar_dir}; choose another place", out_dir)
    existing = [n for n in names if (out_dir / n).exists()]
    if existing and not force:
        raise OutputNotWritable(f"{', '.join(existing)} already exist{'s' if len(existing) == 1 else ''}; "
                                "pass --force to replace", out_dir)
    probe = out_r
    while not probe.exists():  # the nearest existing ancestor must let us create the rest
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise OutputNotWritable(f"{probe} is not writable", out_dir)


def check_output_file(path: Path, avatar_dir: Path, force: bool) -> None:
    """The same refusals for one output file (``fitme render``'s image)."""
    path = Path(path)
    if path.is_dir():
        raise OutputNotWritable("the output path is a directory; give a file name such as sheet.png", path)
    check_output(path.parent, avatar_dir, [path.name], force)


def _write(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)


def export_avatar(avatar_dir: Path, out_dir: Path, settings: ExportSettings = ExportSettings(),
                  shape_model=None) -> ExportResult:
    """Export the avatar in ``avatar_dir`` into ``out_dir``. ``shape_model``: the loaded model (default:
    ``models/``'s, built on first use). Errors: AvatarInvalid, OutputNotWritable, ModelMissing."""
    from ..fitting.avatar import check_shape_model
    from ..io.atomic import publish_file
    from ..io.maps import write_map
    from ..shape.model import load_shape_model
    from .gltf import TEXTURE_SLOTS, glb_bytes, gltf_document
    from .maps import MAP_NAMES, encode_png, exr_arrays, prepare_maps
    from .mesh import build_export_mesh, head_topology
    from .obj import mtl_text, obj_text
    from .source import load_source

    t0 = time.perf_counter()
    out_dir, avatar_dir = Path(out_dir), Path(avatar_dir)
    names = planned_files(settings) + ["export.json"]
    check_output(out_dir, avatar_dir, names, settings.force)
    src = load_source(avatar_dir)
    if shape_model is None:
        from ..perception.registry import ensure_models

        shape_model = load_shape_model(ensure_models(["shape_model"]))
    seconds = {"load": time.perf_counter() - t0}

    t = time.perf_counter()
    fitted = settings.expression == "fitted"
    weights = src.p_e[0] if fitted else None
    check_shape_model(avatar_dir, src.p_s, src.p_e, src.fitted_vertices, shape_model)
    topo = head_topology(shape_model, settings.mesh)
    mesh = build_export_mesh(shape_model, src.p_s, weights, settings.mesh, topo)
    seconds["mesh"] = time.perf_counter() - t

    t = time.perf_counter()
    maps = prepare_maps(src.maps, topo.uv, topo.uv_faces, MapSettings(settings.resolution))
    pngs = {k: encode_png(maps, k) for k in MAP_NAMES} if any(n.endswith(".png") for n in names) or "glb" in settings.formats else {}
    exrs = exr_arrays(maps) if "exr" in settings.maps else {}
    seconds["maps"] = time.perf_counter() - t

    t = time.perf_counter()
    expression = f"fitted ({src.photo_names[0]})" if fitted else "neutral"
    extras = {"fitme": {"units": "metres", "frame": "x to the subject's left, y up, z out of the face",
                        "normal_map": "tangent space, OpenGL convention (+Y up in the image)",
                        "expression": expression, "avatar": avatar_dir.name}}
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".fitme-export.", suffix=".tmp", dir=out_dir))
    except OSError as e:
        raise OutputNotWritable(f"cannot write here: {e.strerror or e}", out_dir) from None
    try:
        try:
            for kind, arr in exrs.items():
                write_map(staging / f"{kind}.exr", arr.astype(np.float32), "exr16")  # float16 -> 32 -> 16 is exact
            for kind, data in pngs.items():
                if f"{kind}.png" in names:
                    _write(staging / f"{kind}.png", data)
            if "glb" in settings.formats:
                doc, binary = gltf_document(mesh, settings.material, images={k: pngs[k] for k in TEXTURE_SLOTS}, extras=extras)
                _write(staging / "head.glb", glb_bytes(doc, binary))
            if "gltf" in settings.formats:
                doc, binary = gltf_document(mesh, settings.material, image_uris={k: f"{k}.png" for k in TEXTURE_SLOTS},
                                            buffer_uri="head.bin", extras=extras)
                _write(staging / "head.bin", binary)
                _write(staging / "head.gltf", (json.dumps(doc, indent=1) + "\n").encode())
            if "obj" in settings.formats:
                geo = mesh.posed if fitted else mesh.neutral
                _write(staging / "head.obj", obj_text(mesh, geo, "head.mtl", settings.material,
                                                      f"fitme export of {avatar_dir.name}: {expression} expression").encode())
                _write(staging / "head.mtl", mtl_text(settings.material, {k: f"{k}.png" for k in MAP_NAMES}).encode())
            sizes = {n: (staging / n).stat().st_size for n in names if n != "export.json"}
            seconds["write"] = time.perf_counter() - t
            seconds["total"] = time.perf_counter() - t0
            manifest = {"avatar": str(avatar_dir), "expression": expression,
                        "settings": {"formats": list(settings.formats), "maps": list(settings.maps),
                                     "resolution": settings.resolution, "mesh": asdict(settings.mesh),
                                     "material": asdict(settings.material) | {"roughness": round(settings.material.roughness, 6),
                                                                              "specular_colour_factor": round(settings.material.specular_colour_factor, 6)}},
                        "conventions": extras["fitme"] | {"texcoords": "OBJ: v up; glTF: t = 1 - v; u wraps at the back seam",
                                                          "albedo": "linear (EXR), sRGB (PNG)", "specular": "linear (EXR), sRGB grey (PNG)",
                                                          "normals_encoding": "n * 0.5 + 0.5"},
                        "mesh": {"vertices": mesh.n_vertices, "triangles": int(len(mesh.faces)),
                                 "morph_targets": len(mesh.target_names)},
                        "maps": {"source_resolution": int(src.maps.albedo.shape[0]), "filled_fraction": round(maps.filled_fraction, 5),
                                 "coverage": round(float(maps.coverage.mean()), 5)},
                        "sizes": sizes, "seconds": {k: round(v, 3) for k, v in seconds.items()}}
            _write(staging / "export.json", (json.dumps(manifest, indent=1) + "\n").encode())
            sizes["export.json"] = (staging / "export.json").stat().st_size
            files = {}
            for n in names:  # all complete: now each rename is atomic
                publish_file(staging / n, out_dir / n)
                files[n] = out_dir / n
        except OSError as e:
            raise OutputNotWritable(f"cannot write: {e.strerror or e}", out_dir) from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return ExportResult(out_dir, files, sizes, seconds, mesh, maps, expression)
