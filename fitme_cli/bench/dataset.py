"""The benchmark set: N synthetic subjects (``fitting/synthetic.make_subject``: random identity,
expression and BRDF-GAN reflectance, random lights and cameras, every effect on, photo-like blur, noise
and JPEG), each seen in three views (0, +30, -30 degrees); the one-view case is the first view.

``BenchSetSettings.reflectance`` "data" takes each subject's maps from the procedural training data instead
(``reflectance/skin_data.py`` at a seed no training set used), not from the shipped generator: subjects that
stay the same when the generator changes, and that no generator can draw exactly, so two generators can be
compared on them (docs/fitting.md "Held-out data subjects").

Written to ``DIR/subject_NN/`` so a run is inspectable and a fit in another process can read it back:
``view_K.png`` (the degraded photos, lossless), ``truth.safetensors`` (p_s, p_e, ws, maps, meshes,
landmarks, cameras, lights) and ``truth.json`` (the synthetic settings, yaws, what each tensor is)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

__all__ = ["BenchSetSettings", "GroundTruth", "make_bench_set", "load_subject", "list_subjects"]


@dataclass(frozen=True)
class BenchSetSettings:
    n_subjects: int = 4
    n_views: int = 3  # each subject's views; the 1-view case fits the first (frontal) one
    size: int = 512  # photo side
    yaw_range_deg: float = 30.0
    blur_sigma: float = 0.7
    noise_sigma: float = 2.0
    jpeg_quality: int = 85
    first_seed: int = 1  # seed 0's -30 degree view finds no face (docs/fitting_synthetic.md)
    reflectance: str = "gan"  # "gan": maps drawn from the shipped BRDF-GAN; "data": held-out procedural maps
    # the skin_data seed of "data" subjects: `fitme dataset` defaults to seed 0, which the shipped BRDF-GAN trained on
    data_seed: int = 1

    def __post_init__(self) -> None:
        if self.reflectance not in ("gan", "data"):
            raise ValueError(f"BenchSetSettings.reflectance must be 'gan' or 'data', got {self.reflectance!r}")
        if self.n_subjects < 1:
            raise ValueError(f"BenchSetSettings.n_subjects must be >= 1, got {self.n_subjects}")
        if self.n_views < 1:
            raise ValueError(f"BenchSetSettings.n_views must be >= 1, got {self.n_views}")


@dataclass(frozen=True)
class GroundTruth:
    """What ``fitting.metrics.evaluate_fit`` needs of a subject, for the views fitted."""

    name: str
    photos: np.ndarray  # (V, H, W, 3) uint8
    ibug68: np.ndarray  # (V, 68, 2) photo px
    vertices: object  # torch (V, N, 3) posed meshes, mm
    neutral: object  # torch (N, 3)
    maps: object  # ReflectanceMaps (1, ., R, R)
    yaws_deg: np.ndarray
    focal_35mm: float

    @property
    def n_views(self) -> int:
        return int(self.photos.shape[0])

    def views(self, idx: list[int]) -> GroundTruth:
        if not idx or max(idx) >= self.n_views or min(idx) < 0:
            raise ValueError(f"GroundTruth.views: indices must be in [0, {self.n_views}), got {idx}")
        return replace(self, photos=self.photos[idx], ibug68=self.ibug68[idx], vertices=self.vertices[idx],
                       yaws_deg=self.yaws_deg[idx])


def _save_subject(d: Path, subject, reflectance: dict) -> None:
    import cv2
    from safetensors.torch import save_file

    d.mkdir(parents=True, exist_ok=True)
    for i, ph in enumerate(subject.photos):
        cv2.imwrite(str(d / f"view_{i}.png"), cv2.cvtColor(ph, cv2.COLOR_RGB2BGR))
    import torch

    c, li = subject.cameras, subject.lights
    t = {"p_s": subject.p_s, "p_e": subject.p_e, "z": subject.z, "ws": subject.ws, "albedo": subject.maps.albedo,
         "specular": subject.maps.specular, "normals": subject.maps.normals, "vertices": subject.vertices,
         "neutral": subject.neutral, "landmarks": torch.from_numpy(subject.landmarks),
         "ibug68": torch.from_numpy(subject.ibug68), "camera_focal": c.focal, "camera_principal": c.principal,
         "camera_rotation": c.rotation, "camera_translation": c.translation, "light_ambient": li.ambient,
         "light_direction": li.direction, "light_colour": li.colour, "light_sh": li.sh}
    save_file({k: v.detach().float().contiguous() for k, v in t.items() if v is not None}, str(d / "truth.safetensors"))
    meta = {"synthetic_settings": asdict(subject.settings), "yaws_deg": subject.yaws_deg.tolist(),
            "effects": subject.effects.on(), "n_views": subject.n_views,
            "z_redraws": subject.z_redraws, "off_tone": round(subject.off_tone, 4), "reflectance": reflectance,
            "tensors": {"p_s": "(1, K) identity, raw shape-model units", "p_e": "(V, E) expression per view",
                        "albedo/specular/normals": "(1, C, R, R) linear maps", "vertices": "(V, N, 3) posed mesh, world mm",
                        "neutral": "(N, 3) identity without expression", "landmarks": "(V, 468, 2) photo px",
                        "ibug68": "(V, 68, 2) photo px", "camera_*": "per view, photo px / world->camera",
                        "light_*": "per view, linear"}}
    (d / "truth.json").write_text(json.dumps(meta, indent=1) + "\n")


def make_bench_set(out: Path, s: BenchSetSettings = BenchSetSettings(), models=None) -> list[Path]:
    """Draw, render and write the subjects (skips a subject whose truth.json already exists with the
    same settings, so a rerun into the same directory is cheap). ``models``: a ``run.FitModels``
    (loaded when None). Returns the subject directories."""
    from ..fitting.synthetic import SyntheticSettings, make_subject
    from .run import load_models

    out = Path(out)
    dirs, held_out = [], None
    for k in range(s.n_subjects):
        seed = s.first_seed + k
        syn = SyntheticSettings(size=s.size, n_views=s.n_views, yaw_range_deg=s.yaw_range_deg, blur_sigma=s.blur_sigma,
                                noise_sigma=s.noise_sigma, jpeg_quality=s.jpeg_quality, background="noise", seed=seed)
        d = out / f"subject_{seed:02d}"
        dirs.append(d)
        source, maps = {"source": s.reflectance}, None
        if s.reflectance == "data":  # drawn for every subject, so that a kept subject's index is not drawn again
            models = models or load_models()
            held_out = held_out or _held_out_maps(models, s.data_seed, syn.max_off_tone)
            index, maps = next(held_out)
            source |= {"seed": s.data_seed, "index": index}
        if (d / "truth.json").exists():
            meta = json.loads((d / "truth.json").read_text())
            if meta["synthetic_settings"] == json.loads(json.dumps(asdict(syn))) and \
                    meta.get("reflectance", {"source": "gan"}) == source:
                continue
        models = models or load_models()
        _save_subject(d, make_subject(models.G, models.shape_model, models.renderer, syn, maps), source)
    return dirs


def _held_out_maps(models, seed: int, max_off_tone: float):
    """Yield (index, ReflectanceMaps (1, ., R, R)) of the procedural data at ``seed`` at the generator's resolution,
    in index order, skipping the samples whose face is more than ``max_off_tone`` off its tone (beards; as
    ``make_subject`` redraws such a z)."""
    import torch

    from ..fitting.synthetic import off_tone_fraction
    from ..reflectance.maps import ReflectanceMaps
    from ..reflectance.skin_data import SkinDataSettings, generate_sample, skin_layout

    r = models.G.settings.resolution
    layout = skin_layout(models.root, r)
    index = 0
    while True:
        smp = generate_sample(layout, seed, index, SkinDataSettings(size=r))
        t = [torch.from_numpy(np.ascontiguousarray(a)).float().reshape(r, r, -1).permute(2, 0, 1)[None]
             for a in (smp.albedo, smp.specular, smp.normals)]
        maps = ReflectanceMaps(*t)
        if off_tone_fraction(maps.albedo, models.shape_model.region_uv) <= max_off_tone:
            yield index, maps
        index += 1


def list_subjects(data_dir: Path) -> list[Path]:
    return sorted(p for p in Path(data_dir).glob("subject_*") if (p / "truth.json").exists())


def load_subject(d: Path) -> GroundTruth:
    """Read a subject written by ``make_bench_set``."""
    import cv2
    from safetensors.torch import load_file

    from ..reflectance.maps import ReflectanceMaps

    d = Path(d)
    if not (d / "truth.json").exists():
        raise FileNotFoundError(f"{d}: no truth.json; expected a subject directory written by make_bench_set")
    meta = json.loads((d / "truth.json").read_text())
    t = load_file(str(d / "truth.safetensors"))
    photos = np.stack([cv2.cvtColor(cv2.imread(str(d / f"view_{i}.png")), cv2.COLOR_BGR2RGB) for i in range(meta["n_views"])])
    return GroundTruth(d.name, photos, t["ibug68"].numpy(), t["vertices"], t["neutral"],
                       ReflectanceMaps(t["albedo"], t["specular"], t["normals"]), np.array(meta["yaws_deg"]),
                       float(meta["synthetic_settings"]["focal_35mm"]))
