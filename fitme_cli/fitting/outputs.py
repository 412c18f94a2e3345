"""Write a fitted avatar into a (staging) directory: parameters, maps, per-photo meshes, landmarks and
panels, the loss curve and avatar.json. Shared by ``fitme fit`` and ``fitme tune``; the layout is in
``avatar.py``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..reflectance.maps import ReflectanceMaps
from .avatar import SCHEMA_VERSION, PhotoRecord, save_params
from .invert import InversionResult, PhotoInput

__all__ = ["PhotoFitQuality", "write_avatar", "obj_text"]


@dataclass(frozen=True)
class PhotoFitQuality:
    """How well one photo is fitted: identity similarity of photo and render (FaceNet cosine, the
    evaluation network: same person is ~0.5 and above); mean distance of the fitted to the detected
    iBUG-68 points in photo pixels and in % of the face width."""

    identity_similarity: float
    landmark_error_px: float
    landmark_error_pct: float


def obj_text(vertices: np.ndarray, faces: np.ndarray, comment: str) -> str:
    """A minimal OBJ (positions and triangles) for inspection tools; exports with UVs are ``fitme export``'s."""
    lines = [f"# {comment}"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def _to_photo(pts: np.ndarray, affine: np.ndarray) -> np.ndarray:
    return pts @ affine[:, :2].T + affine[:, 2]


def write_avatar(out: Path, records: list[PhotoRecord], photos: list[PhotoInput], inv: InversionResult,
                 maps: ReflectanceMaps, tuned: dict[str, torch.Tensor], shape_model, models_root: Path,
                 meta: dict) -> list[PhotoFitQuality]:
    """Write everything into ``out`` (an empty directory). ``maps``: the final maps (after tuning);
    ``meta``: JSON-able settings, timings and histories for avatar.json. Returns each photo's quality."""
    from safetensors.torch import save_file

    from ..io.atomic import atomic_write_bytes, atomic_write_image
    from ..perception.facenet import facenet_embedding_onnx
    from ..reflectance.skin_data import SkinSample, write_sample
    from ..render import Renderer
    from ..render.camera import project
    from ..viz.fit_report import fit_panel, loss_curve

    out = Path(out)
    (out / "maps").mkdir(parents=True, exist_ok=True)
    if tuned:
        save_file({k: v.detach().cpu().contiguous() for k, v in tuned.items()}, str(out / "generator_tuned.safetensors"))
    m = [t.detach().cpu().float() for t in (maps.albedo, maps.specular, maps.normals)]
    sample = SkinSample(m[0][0].permute(1, 2, 0).numpy(), m[1][0, 0].numpy(), m[2][0].permute(1, 2, 0).numpy(), {})
    for fmt in ("png", "exr"):
        write_sample(out / "maps", "avatar", sample, fmt)

    sm = shape_model
    n = len(photos)
    cams = inv.cameras
    with torch.no_grad():
        dev = sm.mean.device
        shp = sm(inv.p_s.to(dev).expand(n, -1), inv.p_e.to(dev))
        save_params(out / "params.safetensors", inv, photos, shp.vertices.cpu())
        renderer = Renderer.for_shape_model(sm).to(dev)
        final = ReflectanceMaps(*(t.to(dev) for t in (maps.albedo, maps.specular, maps.normals)))
        photo_lin = torch.stack([torch.from_numpy(p.crop).permute(2, 0, 1).float() / 255 for p in photos]).to(dev)
        from ..render.shading import srgb_to_linear

        ren = renderer(shp.vertices, shp.normals, shp.tangents, final, cams, inv.lights, inv.effects,
                       background=srgb_to_linear(photo_lin))
        fitted68 = project(shp.vertices[:, sm.ibug68], cams)[..., :2].cpu().numpy()
        cam_space = (torch.einsum("pij,pvj->pvi", cams.rotation, shp.vertices) + cams.translation[:, None]).cpu().numpy()
    faces = sm.triangles.cpu().numpy()
    quality, per_photo = [], []
    for i, (rec, p) in enumerate(zip(records, photos)):
        d = out / "photos" / rec.name
        d.mkdir(parents=True, exist_ok=True)
        img = (ren.image[i].permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        mask = ren.mask[i, 0].cpu().numpy() > 0
        atomic_write_image(d / "panel.png", fit_panel(p.crop, img, mask, p.ibug68, fitted68[i]))
        atomic_write_bytes(d / "mesh_camera.obj", obj_text(
            cam_space[i], faces, f"fitme {rec.name}: fitted mesh in the camera frame (mm; x right, y down, z forward)").encode())
        det_photo, fit_photo = _to_photo(p.ibug68, p.to_photo), _to_photo(fitted68[i], p.to_photo)
        err = float(np.linalg.norm(det_photo - fit_photo, axis=1).mean())
        width = float(np.ptp(det_photo[:, 0]))
        atomic_write_bytes(d / "landmarks68.json", (json.dumps({
            "space": "photo pixels (x right, y down), iBUG-68 order", "fitted": np.round(fit_photo, 2).tolist(),
            "detected": np.round(det_photo, 2).tolist()}) + "\n").encode())
        e_photo = facenet_embedding_onnx(p.crop, p.ibug68, models_root)
        e_render = facenet_embedding_onnx(img, p.ibug68, models_root)  # the render sits where the face was
        q = PhotoFitQuality(float(np.dot(e_photo, e_render)), err, 100 * err / max(width, 1e-6))
        quality.append(q)
        s = abs(p.to_photo[0, 0])  # photo px per crop px
        f = cams.focal[i].cpu().numpy() * s
        c = _to_photo(cams.principal[i].cpu().numpy()[None], p.to_photo)[0]
        per_photo.append({"path": rec.path, "sha256": rec.sha256, "size": list(rec.size),
                          "focal_length_35mm": rec.focal_length_35mm, "name": rec.name,
                          "intrinsics_photo_px": {"focal": np.round(f, 3).tolist(), "principal": np.round(c, 3).tolist()},
                          "quality": {"identity_similarity": round(q.identity_similarity, 4),
                                      "landmark_error_px": round(q.landmark_error_px, 3),
                                      "landmark_error_pct_face_width": round(q.landmark_error_pct, 3)}})
    hist = meta.get("history", {})
    atomic_write_image(out / "loss_curve.png", loss_curve(hist, "fitme: weighted losses"))
    report = {"schema": SCHEMA_VERSION, "inputs": per_photo} | meta
    report["effects"] = {"chosen": inv.effects.on(), "reasons": inv.choice.reasons if inv.choice else {},
                         "coarse_residuals": {k: round(v, 6) for k, v in inv.coarse_residuals.items()}} | meta.get("effects", {})
    report["generator"] = {"resolution": int(maps.albedo.shape[-1]), "tuned_layers": sorted(tuned)}
    atomic_write_bytes(out / "avatar.json", (json.dumps(report, indent=1) + "\n").encode())
    return quality
