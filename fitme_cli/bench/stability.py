"""The whole-fit stability suite: hard photos that must still give a finite, converging fit.

Cases (from one synthetic subject, ``StabilitySettings.seed``, so nothing is downloaded): extreme yaw +-80 degrees (rendered),
strong side light (re-rendered with one light from 80 degrees off the camera and almost no ambient),
very dark (linear x 0.05) and overexposed (linear x 4, clipped) photos, sunglasses (a dark band over the
eyes), a tiny face (the photo at 0.22 x in a 768^2 canvas; also as from a 340 mm lens), heavy JPEG (quality 5) and grayscale; plus
the unmodified photo as a reference. Each case passes when the fit finishes with no NaN / Inf in
parameters, maps or losses (the tuning's too), the inversion's total loss decreases (mean of the last k < mean of
the first k, k = min(5, iterations // 2)) and the maps are in range (albedo and specular in [0, 1], unit normals). A
photo in which detection finds no face passes as a clean failure (NoFaceFound, what ``fitme fit``
reports with exit code 16); any other exception fails."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["StabilitySettings", "StabilityResult", "CASES", "make_cases", "check_fit", "run_stability", "stability_table"]

CASES = ("reference", "yaw +80", "yaw -80", "side light", "very dark", "overexposed", "sunglasses", "tiny face",
         "jpeg q5", "grayscale", "tiny face, telephoto")


@dataclass(frozen=True)
class StabilitySettings:
    iterations: int = 12
    render_size: int = 128
    coarse_fraction: float = 0.0  # the fast preset's (no coarse phase; 0.6 until 2026-11-25)
    size: int = 512  # synthetic photo side
    # the subject must be one the detector finds in every degraded copy but the extreme yaws, or the suite
    # tests detection, not fit stability. Synthetic renders have no eyeballs (docs/perception.md, "Skin
    # tone"; real photos re-toned to every Monk level are found, tests/test_detect.py), and BlazeFace scores
    # them near its threshold: seed 3 (the suite's subject until 2026-11-25) lost its grayscale copy on an
    # AVX2 machine, where FaceMesh's presence after the landmark passes fell below 0.5. Seed 0 at a score
    # threshold of 0.3 (FaceMesh's presence still rejects false boxes): every non-yaw copy found with
    # presence 1.00 and a BlazeFace score of 0.44 (sunglasses) to 0.89 (measured on that machine)
    seed: int = 0
    detect_score: float = 0.3
    cases: tuple[str, ...] = CASES

    def __post_init__(self) -> None:
        if not 0 < self.detect_score < 1:
            raise ValueError(f"StabilitySettings.detect_score must be in (0, 1), got {self.detect_score}")
        if self.iterations < 2:
            raise ValueError(f"StabilitySettings.iterations must be >= 2 (the loss must be seen to decrease), got {self.iterations}")
        bad = [c for c in self.cases if c not in CASES]
        if bad:
            raise ValueError(f"StabilitySettings.cases: unknown {bad}; expected some of {', '.join(CASES)}")


@dataclass(frozen=True)
class StabilityResult:
    case: str
    passed: bool
    kind: str  # "fit" (a fit that met every check), "clean failure" (no face found) or "fail"
    detail: str  # what failed, or the clean error's message
    first_loss: float = math.nan  # mean total loss over the first k iterations
    last_loss: float = math.nan
    identity_sim: float = math.nan
    landmark_px: float = math.nan  # fit vs detected iBUG-68, photo px
    fit_s: float = math.nan
    checks: dict[str, bool] = field(default_factory=dict)


def _srgb_to_lin(x: np.ndarray) -> np.ndarray:
    """uint8 sRGB -> float32 linear (the curve of io.maps)."""
    from ..io.maps import srgb_to_linear

    return srgb_to_linear(x.astype(np.float32) / 255)


def _lin_to_srgb(x: np.ndarray) -> np.ndarray:
    """linear (clipped to [0, 1]) -> uint8 sRGB."""
    from ..io.maps import linear_to_srgb

    return np.clip(np.round(linear_to_srgb(x) * 255), 0, 255).astype(np.uint8)


def _jpeg(img: np.ndarray, q: int) -> np.ndarray:
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, q])
    if not ok:
        raise RuntimeError("cv2.imencode failed to write a JPEG")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _photo_like(img: np.ndarray, rng: np.random.Generator, noise: float = 2.0, q: int = 90) -> np.ndarray:
    import cv2

    x = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7) + rng.normal(0, noise, img.shape).astype(np.float32)
    return _jpeg(np.clip(np.round(x), 0, 255).astype(np.uint8), q)


def _side_light(subject, models, rng) -> np.ndarray:
    """The subject re-rendered with one strong light from the camera's side (80 degrees off the view
    direction), ambient 0.02: half the face in near-black shadow."""
    import torch

    from ..render import Effects, Lights

    cam = subject.cameras
    r, t = cam.rotation[0].double(), cam.translation[0].double()
    eye = -(r.T @ t)
    view = eye / eye.norm()
    right = r[0]  # the camera's x axis in the world
    a = math.radians(80)
    d = (math.cos(a) * view + math.sin(a) * right).float()
    lights = Lights(torch.full((1, 3), 0.02), d.view(1, 1, 3), torch.full((1, 1, 3), 1.6))
    sm = models.shape_model
    with torch.no_grad():
        shp = sm(subject.p_s, subject.p_e[:1])
        from ..render.camera import Camera

        c1 = Camera(cam.focal[:1], cam.principal[:1], cam.rotation[:1], cam.translation[:1], cam.width, cam.height)
        # every effect but the SH environment: the constant ambient is the point (almost none)
        out = models.renderer(shp.vertices, shp.normals, shp.tangents, subject.maps, c1, lights,
                              Effects(sh_ambient=False, shadows=True, multi_light=True),
                              background=torch.full((1, 3, cam.height, cam.width), 0.08))
    img = (out.image[0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    return _photo_like(img, rng)


def make_cases(models, s: StabilitySettings = StabilitySettings()) -> dict[str, tuple[np.ndarray, float]]:
    """{case: (photo (H, W, 3) uint8, focal_35mm)} for the settings' cases."""
    import cv2

    from ..fitting.synthetic import SyntheticSettings, make_subject

    rng = np.random.default_rng(s.seed)
    # max_off_tone 1: seed 0's z is kept although bearded (a beard is one more hard case here, and the
    # suite's figures in docs/benchmarks.md are this subject's)
    base_s = SyntheticSettings(size=s.size, n_views=1, seed=s.seed, background="noise", max_off_tone=1.0)
    base = make_subject(models.G, models.shape_model, models.renderer, base_s)
    f = base_s.focal_35mm
    photo = base.photos[0]
    out: dict[str, tuple[np.ndarray, float]] = {}
    want = set(s.cases)
    if "reference" in want:
        out["reference"] = (photo, f)
    if want & {"yaw +80", "yaw -80"}:
        turned = make_subject(models.G, models.shape_model, models.renderer,
                              SyntheticSettings(size=s.size, n_views=3, yaw_range_deg=80, seed=s.seed, background="noise",
                                                max_off_tone=1.0))
        out["yaw +80"], out["yaw -80"] = (turned.photos[1], f), (turned.photos[2], f)
    if "side light" in want:
        out["side light"] = (_side_light(base, models, rng), f)
    lin = _srgb_to_lin(photo)
    if "very dark" in want:  # a dark room: the signal near the sensor noise, then quantised
        out["very dark"] = (_lin_to_srgb(lin * 0.05 + rng.normal(0, 0.0015, lin.shape)), f)
    if "overexposed" in want:
        out["overexposed"] = (_lin_to_srgb(lin * 4.0), f)
    if "sunglasses" in want:
        eyes = base.ibug68[0, 36:48]
        lo, hi = eyes.min(0), eyes.max(0)
        h = hi[1] - lo[1]
        img = photo.copy()
        x0, x1 = int(lo[0] - 0.25 * (hi[0] - lo[0])), int(hi[0] + 0.25 * (hi[0] - lo[0]))
        y0, y1 = int(lo[1] - 1.5 * h - 4), int(hi[1] + 1.5 * h + 4)
        cv2.rectangle(img, (x0, y0), (x1, y1), (12, 12, 14), thickness=-1)
        out["sunglasses"] = (img, f)
    if want & {"tiny face", "tiny face, telephoto"}:
        small = cv2.resize(photo, None, fx=0.22, fy=0.22, interpolation=cv2.INTER_AREA)
        canvas = np.full((768, 768, 3), photo[2, 2], np.uint8)
        y = x = (768 - small.shape[0]) // 2
        canvas[y:y + small.shape[0], x:x + small.shape[1]] = small
        if "tiny face" in want:
            out["tiny face"] = (canvas, f)  # the same lens, the person further away
    if "tiny face, telephoto" in want:  # the same canvas from a 340 mm (35 mm equivalent) lens: the face spans < 1 degree
        out["tiny face, telephoto"] = (canvas, f * 768 / (0.22 * s.size))
    if "jpeg q5" in want:
        out["jpeg q5"] = (_jpeg(photo, 5), f)
    if "grayscale" in want:
        g = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
        out["grayscale"] = (np.repeat(g[..., None], 3, -1), f)
    return {c: out[c] for c in s.cases}


def _finite(x) -> bool:
    import torch

    if x is None:
        return True
    if isinstance(x, torch.Tensor):
        return bool(torch.isfinite(x).all())
    return all(math.isfinite(v) for v in np.ravel(np.asarray(x, np.float64)))


def check_fit(inv, maps, history: list[dict[str, float]], tol: float = 1e-4,
              tune_history: list[dict[str, float]] = ()) -> dict[str, bool]:
    """The stability checks on an inversion result, the final maps, the inversion's loss history and the tuning's:
    {check: passed}. The loss must fall over the inversion; the tuning's totals sum other terms, so they are only
    checked for being finite."""
    import torch

    if not history:
        raise ValueError("check_fit: empty loss history; expected one record per iteration")
    cam, li = inv.cameras, inv.lights
    params = [inv.ws, inv.p_s, inv.p_e, cam.focal, cam.principal, cam.rotation, cam.translation, li.ambient, li.direction,
              li.colour, li.sh]
    totals = np.array([h["total"] for h in history])
    k = min(5, len(totals) // 2) or 1
    nrm = torch.linalg.vector_norm(maps.normals, dim=1)
    return {
        "finite params": all(_finite(p) for p in params),
        "finite maps": all(_finite(t) for t in (maps.albedo, maps.specular, maps.normals)),
        "finite losses": all(_finite(list(h.values())) for h in history),
        "finite tuning losses": all(_finite(list(h.values())) for h in tune_history),
        "loss decreases": bool(totals[-k:].mean() < totals[:k].mean()),
        "albedo in [0, 1]": bool(maps.albedo.min() >= -tol and maps.albedo.max() <= 1 + tol),
        "specular in [0, 1]": bool(maps.specular.min() >= -tol and maps.specular.max() <= 1 + tol),
        "unit normals": bool((nrm - 1).abs().max() <= 1e-2),
    }


def run_stability(models=None, s: StabilitySettings = StabilitySettings(), log=lambda msg: None) -> list[StabilityResult]:
    from ..errors import NoFaceFound
    from .run import FitSettings, fit_photos, load_models

    models = models or load_models()
    fs = FitSettings.from_preset("fast", iterations=s.iterations, render_size=s.render_size, coarse_fraction=s.coarse_fraction)
    results = []
    for case, (photo, focal) in make_cases(models, s).items():
        t = time.perf_counter()
        try:
            o = fit_photos([photo], models, fs, focal, detect_score=s.detect_score)
        except NoFaceFound as e:
            results.append(StabilityResult(case, True, "clean failure", f"no face (clean error): {e}"))
            log(f"stability: {case}: no face (clean error)")
            continue
        except Exception as e:  # noqa: BLE001 - a crash is this suite's failure, reported per case
            results.append(StabilityResult(case, False, "fail", f"crash: {type(e).__name__}: {e}"[:300]))
            log(f"stability: {case}: CRASH {type(e).__name__}: {e}")
            continue
        checks = check_fit(o.inversion, o.maps, o.inversion.history, tune_history=o.tune_history)
        totals = np.array([h["total"] for h in o.inversion.history])
        k = min(5, len(totals) // 2) or 1
        ok = all(checks.values())
        bad = [c for c, v in checks.items() if not v]
        r = StabilityResult(case, ok, "fit" if ok else "fail", "ok" if ok else "failed: " + ", ".join(bad),
                            float(totals[:k].mean()), float(totals[-k:].mean()), o.metrics.identity_sim,
                            o.metrics.landmark_px, time.perf_counter() - t, checks)
        results.append(r)
        log(f"stability: {case}: {r.detail} ({r.fit_s:.1f} s)")
    return results


def stability_table(results: list[StabilityResult]) -> str:
    def f(x, nd):
        return "–" if not math.isfinite(x) else f"{x:.{nd}f}"
    rows = ["| case | result | loss first k → last k | identity sim | landmarks px (fit vs detected) | time s | detail |",
            "|---|---|---|---:|---:|---:|---|"]
    for r in results:
        res = "pass" if r.passed and r.kind == "fit" else ("pass (clean failure)" if r.passed else "**FAIL**")
        rows.append(f"| {r.case} | {res} | {f(r.first_loss, 3)} → {f(r.last_loss, 3)} | {f(r.identity_sim, 3)} | "
                    f"{f(r.landmark_px, 2)} | {f(r.fit_s, 1)} | {' '.join(r.detail.split()).replace('|', '/')} |")
    return "\n".join(rows) + "\n"
