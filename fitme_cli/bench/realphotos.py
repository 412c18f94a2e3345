"""Real photos (no ground truth): how much the fit's render looks like the person, judged by the
evaluation network (FaceNet, not the dlib descriptor the fit optimises), against what the same network
says of other photos of the same person and of different people.

People: every subfolder of ``--photos DIR`` (one per person, any number of photos) plus the sample
photos shipped in packages (astronaut, grace_hopper, camera: three different people)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["RealPhotoResult", "collect_photos", "run_real_photos", "real_photos_table"]

SAMPLES = ("astronaut", "grace_hopper", "camera")
_EXTS = {".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff", ".heic"}


@dataclass(frozen=True)
class RealPhotoResult:
    person: str
    photo: str
    status: str  # "ok", "no face" or "error: ..."
    render_sim: float = math.nan  # FaceNet cosine of the photo crop vs the render of its fit
    same_person_sim: float = math.nan  # mean cosine to the person's other photos (NaN: only one photo)
    other_people_sim: float = math.nan  # mean cosine to every photo of every other person
    other_people_max: float = math.nan
    landmark_px: float = math.nan
    fit_s: float = math.nan


def collect_photos(photos_dir: Path | None, samples: tuple[str, ...] = SAMPLES) -> list[tuple[str, str, np.ndarray, float | None]]:
    """[(person, name, rgb, focal_35mm)]: the sample photos, then DIR/PERSON/*.{jpg,png,...}."""
    from ..io.images import load_image, sample_photo

    out = []
    for s in samples:
        img = sample_photo(s)
        out.append((s, s, img.rgb, img.focal_length_35mm))
    if photos_dir is not None:
        d = Path(photos_dir)
        if not d.is_dir():
            raise ValueError(f"{d} is not a directory; expected one subfolder per person")
        people = sorted(p for p in d.iterdir() if p.is_dir())
        if not people:
            raise ValueError(f"{d} has no subfolders; expected one subfolder per person")
        for person in people:
            for f in sorted(person.iterdir()):
                if f.suffix.lower() in _EXTS:
                    img = load_image(f)
                    out.append((person.name, f"{person.name}/{f.name}", img.rgb, img.focal_length_35mm))
    return out


def run_real_photos(models, photos: list[tuple[str, str, np.ndarray, float | None]], settings, fit_people=None,
                    log=lambda msg: None) -> list[RealPhotoResult]:
    """Embed every photo, fit those of ``fit_people`` (None: all) with ``settings`` (a ``FitSettings``)."""
    from ..errors import FitmeError
    from ..perception.detect import DetectSettings, detect
    from ..perception.facenet import facenet_embedding_onnx
    from .run import fit_photos

    emb: dict[str, np.ndarray] = {}
    for person, name, rgb, _ in photos:
        try:
            lm = detect(rgb, DetectSettings(identity=False)).face.landmarks
            emb[name] = facenet_embedding_onnx(rgb, lm.ibug68, models.root)
        except FitmeError:
            pass
    results = []
    for person, name, rgb, focal in photos:
        if name not in emb:
            results.append(RealPhotoResult(person, name, "no face"))
            continue
        same = [float(emb[name] @ emb[n]) for p, n, _, _ in photos if p == person and n != name and n in emb]
        other = [float(emb[name] @ emb[n]) for p, n, _, _ in photos if p != person and n in emb]
        kw = dict(same_person_sim=float(np.mean(same)) if same else math.nan,
                  other_people_sim=float(np.mean(other)) if other else math.nan,
                  other_people_max=max(other) if other else math.nan)
        if fit_people is not None and person not in fit_people:
            results.append(RealPhotoResult(person, name, "not fitted", **kw))
            continue
        try:
            m = fit_photos([rgb], models, settings, focal).metrics
        except FitmeError as e:
            results.append(RealPhotoResult(person, name, f"error: {e}", **kw))
            continue
        results.append(RealPhotoResult(person, name, "ok", m.identity_sim, landmark_px=m.landmark_px, fit_s=m.fit_s, **kw))
        log(f"bench: real photo {name}: render similarity {m.identity_sim:.3f} ({m.fit_s:.1f} s)")
    return results


def real_photos_table(results: list[RealPhotoResult]) -> str:
    def f(x):
        return "–" if not math.isfinite(x) else f"{x:.3f}"
    rows = ["| person | photo | status | photo vs render of its fit | vs same person's other photos (mean) | "
            "vs other people (mean / max) | landmarks px (fit vs detected) | fit s |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in results:
        rows.append(f"| {r.person} | {r.photo} | {r.status} | {f(r.render_sim)} | {f(r.same_person_sim)} | "
                    f"{f(r.other_people_sim)} / {f(r.other_people_max)} | {f(r.landmark_px)} | "
                    f"{'–' if not math.isfinite(r.fit_s) else f'{r.fit_s:.1f}'} |")
    return "\n".join(rows) + "\n"
