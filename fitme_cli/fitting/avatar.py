"""The avatar directory: what ``fitme fit`` writes and ``fitme tune`` / ``fitme export`` read.

Layout (schema ``SCHEMA_VERSION``; docs/avatar_format.md describes every field):

    avatar.json                  inputs and hashes, settings, effects and the selector's reasons,
                                 timings, final losses, per-photo intrinsics and identity similarity
    params.safetensors           W, p_s, p_e, cameras, lights, and each photo's prepared crop (so that
                                 ``tune`` needs nothing outside the directory)
    generator_tuned.safetensors  the tuned generator layers (state-dict names), when tuned
    maps/avatar_{albedo,specular,normals}.{png,exr}   at the generator's resolution
    photos/NAME/mesh_camera.obj  the fitted mesh (with its expression) in that photo's camera frame
    photos/NAME/landmarks68.json the fitted and the detected iBUG-68 points, photo pixels
    photos/NAME/panel.png        photo | landmarks overlay | render | difference
    loss_curve.png               the losses per iteration

Writing is atomic for the whole directory: everything goes to a hidden sibling, which then replaces
the target in one ``renameat2(RENAME_EXCHANGE)`` (Linux), or two renames elsewhere. A kill leaves the
old avatar or the complete new one.
"""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import AvatarInvalid, ModelMismatch, OutputNotWritable
from ..reflectance.maps import ReflectanceMaps
from ..render import Camera, Effects, Lights
from .invert import InversionResult, PhotoInput

__all__ = ["SCHEMA_VERSION", "SHAPE_TOLERANCE_MM", "MAPS_TOLERANCE", "PhotoRecord", "Avatar", "check_output_dir",
           "staging_dir", "publish_dir", "save_params", "load_avatar", "read_fitted_vertices", "check_shape_model",
           "check_generator"]

SCHEMA_VERSION = "1.2"  # 1.1: params.noise_gain; 1.2: params.fitted_vertices
# The same shape model rebuilt on another BLAS differs by ~1e-12 mm, a float32 fit on another device by
# ~1e-4 mm; a changed basis (converter 1 -> 2) moves a fitted face by millimetres.
SHAPE_TOLERANCE_MM = 0.05
# Mean |difference| of the albedo regenerated from W and the one the avatar holds: 2e-5 for the same
# generator (half-float EXR); 0.002 after dropping 3 tuning iterations; 0.019 for a G 26 kimg apart.
MAPS_TOLERANCE = 0.001


@dataclass(frozen=True)
class PhotoRecord:
    """One input photo: where it was, its SHA-256, its size (W, H) and its focal length (35 mm equivalent
    from EXIF, or None); ``name``: the stem used for its files in the avatar."""

    path: str
    sha256: str
    size: tuple[int, int]
    focal_length_35mm: float | None
    name: str


@dataclass(frozen=True)
class Avatar:
    """A loaded avatar directory. ``report``: avatar.json as written; ``photos``: the prepared crops;
    ``inversion``: the fitted parameters (history from avatar.json); ``tuned``: the tuned generator layers
    (empty when not tuned); ``fitted_vertices``: (P, V, 3) float32 mm, shape-model frame, the meshes the fit
    made (None when the avatar records none), for ``check_shape_model``."""

    path: Path
    report: dict
    records: list[PhotoRecord]
    photos: list[PhotoInput]
    inversion: InversionResult
    tuned: dict[str, torch.Tensor]
    fitted_vertices: torch.Tensor | None


def check_output_dir(out_dir: Path, inputs: list[Path], force: bool) -> None:
    """Refuse before any work: a file in the way, an input inside, or a non-empty directory without --force."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputNotWritable("the avatar path exists and is not a directory", out_dir)
    resolved = out_dir.resolve()
    for p in inputs:
        if p.exists() and (p.resolve() == resolved or resolved in p.resolve().parents):
            raise OutputNotWritable(f"the avatar directory would contain or replace the input {p}", out_dir)
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if not (out_dir / "avatar.json").is_file():
            # --force replaces the whole directory: never one that holds something other than an avatar
            raise OutputNotWritable("the directory holds files and is not an avatar; choose a new or empty directory", out_dir)
        if not force:
            raise OutputNotWritable("the directory holds an avatar; pass --force to replace it", out_dir)
    parent = resolved.parent
    if not parent.exists():
        try:
            parent.mkdir(parents=True)
        except OSError as e:
            raise OutputNotWritable(f"cannot create {parent}: {e.strerror}", out_dir) from None
    if not os.access(parent, os.W_OK):
        raise OutputNotWritable(f"{parent} is not writable", out_dir)


def staging_dir(out_dir: Path) -> Path:
    """A fresh hidden directory beside ``out_dir`` (same file system, so the final rename is atomic)."""
    out_dir = Path(out_dir).resolve()
    try:
        return Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    except OSError as e:
        raise OutputNotWritable(f"cannot write beside the avatar directory: {e.strerror}", out_dir) from None


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), rename_exchange) == 0


def publish_dir(staging: Path, out_dir: Path) -> None:
    """Make the finished ``staging`` directory ``out_dir``, replacing what was there."""
    out_dir = Path(out_dir).resolve()
    os.chmod(staging, 0o777 & ~_umask())
    if not out_dir.exists():
        os.rename(staging, out_dir)
        return
    if _exchange(staging, out_dir):
        shutil.rmtree(staging, ignore_errors=True)  # now holds the old avatar
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".old", dir=out_dir.parent))
    os.rmdir(old)
    os.rename(out_dir, old)
    os.rename(staging, out_dir)
    shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_params(path: Path, inv: InversionResult, photos: list[PhotoInput], vertices: torch.Tensor) -> None:
    """params.safetensors: the fitted parameters (crop-pixel cameras), the prepared photos, and
    ``vertices``: (P, V, 3) mm, the shape model's meshes for p_s and each photo's p_e."""
    from safetensors.torch import save_file

    c, li = inv.cameras, inv.lights
    t = {"ws": inv.ws, "p_s": inv.p_s, "p_e": inv.p_e, "camera_focal": c.focal, "camera_principal": c.principal,
         "camera_rotation": c.rotation, "camera_translation": c.translation, "light_ambient": li.ambient,
         "light_direction": li.direction, "light_colour": li.colour,
         "photo_crop": torch.from_numpy(np.stack([p.crop for p in photos])),
         "photo_landmarks": torch.from_numpy(np.stack([p.landmarks for p in photos])),
         "photo_ibug68": torch.from_numpy(np.stack([p.ibug68 for p in photos])),
         "photo_skin": torch.from_numpy(np.stack([p.skin for p in photos]).astype(np.float32)),
         "photo_focal_px": torch.tensor([p.focal_px for p in photos], dtype=torch.float64),
         "photo_principal": torch.from_numpy(np.stack([p.principal for p in photos]).astype(np.float64)),
         "photo_to_photo": torch.from_numpy(np.stack([p.to_photo for p in photos]).astype(np.float64))}
    if li.sh is not None:
        t["light_sh"] = li.sh
    t["noise_gain"] = torch.tensor([inv.noise_gain], dtype=torch.float64)
    t["fitted_vertices"] = vertices.float()
    save_file({k: v.detach().cpu().contiguous() for k, v in t.items()}, str(path))


def load_avatar(path: Path) -> Avatar:
    """Read an avatar directory written by ``fitme fit``; AvatarInvalid says what is missing or wrong."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_dir():
        raise AvatarInvalid("not an avatar directory (missing, or not a directory)", path)
    try:
        report = json.loads((path / "avatar.json").read_text())
    except FileNotFoundError:
        raise AvatarInvalid("no avatar.json: not an avatar directory", path) from None
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise AvatarInvalid(f"avatar.json is unreadable: {e}", path) from None
    major = str(report.get("schema", "")).split(".")[0]
    if major != SCHEMA_VERSION.split(".")[0]:
        raise AvatarInvalid(f"avatar schema {report.get('schema')!r}, this fitme reads {SCHEMA_VERSION}", path)
    try:
        t = load_file(str(path / "params.safetensors"))
        tuned = load_file(str(path / "generator_tuned.safetensors")) if (path / "generator_tuned.safetensors").exists() else {}
    except (OSError, SafetensorError) as e:
        raise AvatarInvalid(f"params are unreadable: {e}", path) from None
    need = ("ws", "p_s", "p_e", "camera_focal", "camera_principal", "camera_rotation", "camera_translation",
            "light_ambient", "light_direction", "light_colour", "photo_crop", "photo_landmarks", "photo_ibug68",
            "photo_skin", "photo_focal_px", "photo_principal", "photo_to_photo")
    missing = [k for k in need if k not in t]
    if missing:
        raise AvatarInvalid(f"params.safetensors lacks {', '.join(missing)}", path)
    try:
        records = [PhotoRecord(r["path"], r["sha256"], tuple(r["size"]), r.get("focal_length_35mm"), r["name"])
                   for r in report["inputs"]]
        n = len(records)
        size = int(t["photo_crop"].shape[1])
        cam = Camera(t["camera_focal"], t["camera_principal"], t["camera_rotation"], t["camera_translation"], size, size)
        lights = Lights(t["light_ambient"], t["light_direction"], t["light_colour"], sh=t.get("light_sh"))
        photos = [PhotoInput(t["photo_crop"][i].numpy(), t["photo_landmarks"][i].numpy(), t["photo_ibug68"][i].numpy(),
                             t["photo_skin"][i].numpy(), float(t["photo_focal_px"][i]), t["photo_principal"][i].numpy(),
                             t["photo_to_photo"][i].numpy()) for i in range(n)]
        effects = Effects(**{k: k in report["effects"]["chosen"] for k in Effects().__dataclass_fields__})
        history = report.get("history", {}).get("inversion", [])
        if cam.batch != n or t["p_e"].shape[0] != n:
            raise ValueError(f"{n} inputs but parameters for {cam.batch} photos")
    except (KeyError, TypeError, ValueError) as e:
        raise AvatarInvalid(f"avatar.json and params disagree or lack a field: {e}", path) from None
    empty = ReflectanceMaps(torch.zeros(1, 3, 1, 1), torch.zeros(1, 1, 1, 1), torch.zeros(1, 3, 1, 1))
    inv = InversionResult(t["ws"], t["p_s"], t["p_e"], cam, lights, empty, history, effects, None,
                          report.get("effects", {}).get("coarse_residuals", {}),
                          float(t["noise_gain"][0]) if "noise_gain" in t else 1.0)  # avatars before it: full noise
    fitted = t.get("fitted_vertices")
    if fitted is None:  # schema < 1.2: the per-photo OBJs hold the same meshes in camera frames
        fitted = read_fitted_vertices(path, [r.name for r in records], cam.rotation, cam.translation)
    return Avatar(path, report, records, photos, inv, tuned, fitted)


def read_fitted_vertices(path: Path, names: list[str], rotation: torch.Tensor,
                         translation: torch.Tensor) -> torch.Tensor | None:
    """(P, V, 3) float32 mm, shape-model frame, from photos/NAME/mesh_camera.obj (camera frame, 4 decimals)
    and the fitted world-to-camera ``rotation`` (P, 3, 3) and ``translation`` (P, 3); None when any is
    missing or unreadable."""
    meshes = []
    for i, name in enumerate(names):
        try:
            with open(path / "photos" / name / "mesh_camera.obj") as f:
                v = np.array([line.split()[1:4] for line in f if line.startswith("v ")], dtype=np.float64)
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if v.ndim != 2 or v.shape[1] != 3 or (meshes and v.shape != meshes[0].shape):
            return None
        r, t = rotation[i].double().numpy(), translation[i].double().numpy()
        meshes.append((v - t) @ r)  # camera = R world + t
    return torch.from_numpy(np.stack(meshes)).float()


def check_shape_model(path: Path, p_s, p_e, fitted_vertices, shape_model) -> float:
    """Refuse an avatar that the shape model in use no longer turns into the face that was fitted.

    ``p_s``: (K,) or (1, K); ``p_e``: (P, E) (tensors or arrays); ``fitted_vertices``: (P, V, 3) mm or None
    (an avatar recording no mesh). Returns the largest vertex shift in mm; raises ModelMismatch when it
    exceeds SHAPE_TOLERANCE_MM or the coefficient counts differ."""
    sm = shape_model
    p_s = torch.as_tensor(p_s).detach().cpu().float().reshape(1, -1)
    p_e = torch.as_tensor(p_e).detach().cpu().float()
    p_e = p_e.reshape(-1, p_e.shape[-1])
    if p_s.shape[1] != sm.n_identity or p_e.shape[1] != sm.n_expressions:
        raise ModelMismatch(f"params have {p_s.shape[1]} identity and {p_e.shape[1]} expression coefficients; the "
                            f"shape model has {sm.n_identity} and {sm.n_expressions}: refit the photos with fitme fit", path)
    if fitted_vertices is None:
        raise ModelMismatch("the avatar records no fitted mesh (params.fitted_vertices or photos/*/mesh_camera.obj), "
                            "so it cannot be checked against the shape model in models/: refit the photos with fitme fit", path)
    ref = torch.as_tensor(fitted_vertices).float()
    with torch.no_grad():
        dev = sm.mean.device
        v = sm.vertices(p_s.to(dev).expand(p_e.shape[0], -1), p_e.to(dev)).float().cpu()
    if v.shape != ref.shape:
        raise ModelMismatch(f"fitted meshes of shape {tuple(ref.shape)}, the shape model makes {tuple(v.shape)}: "
                            "refit the photos with fitme fit", path)
    shift = float((v - ref).norm(dim=-1).max())
    if not shift <= SHAPE_TOLERANCE_MM:
        raise ModelMismatch(f"models/shape_model is not the shape model this avatar was fitted with: its coefficients "
                            f"now give a face up to {shift:.2f} mm away (tolerance {SHAPE_TOLERANCE_MM} mm); "
                            "refit the photos with fitme fit", path)
    return shift


def check_generator(path: Path, albedo: torch.Tensor) -> float:
    """Refuse an avatar whose W no longer makes its maps under the generator in use (another BRDF-GAN).

    ``albedo``: (1, 3, R, R) linear [0, 1], regenerated from the avatar's W (and tuned layers); compared
    with maps/avatar_albedo.exr. Returns the mean |difference|; raises ModelMismatch above MAPS_TOLERANCE."""
    from ..errors import FitmeError
    from ..io.maps import read_map

    try:
        held = torch.from_numpy(np.ascontiguousarray(read_map(path / "maps" / "avatar_albedo.exr").linear)).permute(2, 0, 1)
    except FitmeError as e:
        raise AvatarInvalid(f"maps/avatar_albedo.exr is unreadable: {e.message}", path) from None
    now = albedo.detach().float().cpu()[0]
    if now.shape != held.shape:
        raise ModelMismatch(f"the avatar's maps are {tuple(held.shape)}, the generator in models/ makes {tuple(now.shape)}: "
                            "refit the photos with fitme fit", path)
    gap = float((now - held).abs().mean())
    if not gap <= MAPS_TOLERANCE:
        raise ModelMismatch(f"models/brdf_gan is not the generator this avatar was fitted with: its W now makes an albedo "
                            f"{gap:.3f} away on average (tolerance {MAPS_TOLERANCE}); refit the photos with fitme fit", path)
    return gap
