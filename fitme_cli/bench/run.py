"""One fit as ``fitme fit`` runs it (detect -> prepare_photo -> invert -> tune), in process, with the
measurements the benchmark needs: fit time, the per-photo identity similarity by the evaluation
network (FaceNet, as ``fitting/outputs.py``), the photometric error of the final render and, when
ground truth is given, every ``fitting/metrics.py`` metric."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["FitSettings", "FitModels", "FitMetrics", "FitOutcome", "load_models", "fit_photos", "METRICS"]

# name -> True when larger is better; the accuracy metrics a run reports (NaN where not measurable,
# e.g. the ground-truth ones on a real photo)
METRICS: dict[str, bool] = {
    "landmark_px": False,  # iBUG-68 vertices of the fit vs the truth (synthetic) or the detector (real), photo px
    "shape_mm": False,  # neutral identity mesh, face region, point to surface after rigid alignment
    "shape_posed_mm": False,  # each photo's posed mesh, same measure
    "albedo_l1": False,  # linear L1 on the face texels
    "albedo_delta_e": False,  # CIE76 Delta E on the face texels
    "albedo_delta_e_gain": False,  # after the per-channel gain (albedo scale trades off with light intensity)
    "normals_deg": False,  # detail normals, face texels
    "identity_sim": True,  # FaceNet cosine of photo crop vs render over it, mean over photos
    "photometric": False,  # mean |render - photo| over skin covered by the mesh, 8-bit sRGB levels
}


@dataclass(frozen=True)
class FitSettings:
    """The knobs of one fit; the defaults are the fast preset (``fitting/presets.py``)."""

    iterations: int = 30
    tune_iterations: int = 20
    render_size: int = 128
    coarse_fraction: float = 0.0
    coarse_resolution: int = 128
    select_effects: bool = False
    forced_effects: tuple[tuple[str, bool], ...] = ()
    seed: int = 0
    start_jitter: float = 0.0  # InversionSettings.start_jitter

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"FitSettings.iterations must be >= 1, got {self.iterations}")
        if self.tune_iterations < 0:
            raise ValueError(f"FitSettings.tune_iterations must be >= 0, got {self.tune_iterations}")
        if self.render_size < 64:
            raise ValueError(f"FitSettings.render_size must be >= 64, got {self.render_size}")
        if not 0 <= self.coarse_fraction <= 1:
            raise ValueError(f"FitSettings.coarse_fraction must be in [0, 1], got {self.coarse_fraction}")
        from ..render.effects import EFFECT_NAMES

        for name, _ in self.forced_effects:
            if name not in EFFECT_NAMES:
                raise ValueError(f"FitSettings.forced_effects: unknown effect {name!r}; expected one of {', '.join(EFFECT_NAMES)}")

    def member(self, m: int, jitter: float) -> FitSettings:
        """The m-th member of an ensemble of fits: member 0 is these settings, member m > 0 starts from
        w_avg nudged by ``jitter`` (seeded by m): ``fitting.invert.member_settings``."""
        from ..fitting.invert import member_settings

        return member_settings(self, m, jitter)

    @staticmethod
    def from_preset(name: str, **overrides) -> FitSettings:
        from ..fitting.presets import preset

        p = preset(name)
        base = {"iterations": p.iterations, "tune_iterations": p.tune_iterations, "render_size": p.render_size,
                "coarse_fraction": p.coarse_fraction, "coarse_resolution": p.coarse_resolution,
                "select_effects": p.select_effects}
        return FitSettings(**(base | overrides))


@dataclass
class FitModels:
    """Everything a fit loads once: generator, shape model, dlib descriptor, W prior, FaceMesh topology."""

    root: Path
    G: object
    shape_model: object
    descriptor: object
    prior: object
    topology: object
    renderer: object
    _g_state: dict = field(default_factory=dict, repr=False)

    def restore_generator(self) -> None:
        """Undo tuning: ``tune`` trains the generator's middle layers in place."""
        self.G.load_state_dict(self._g_state)


def load_models() -> FitModels:
    from ..perception.dlib_resnet import load_dlib_resnet
    from ..perception.registry import ensure_models
    from ..reflectance.gan.store import load_generator, load_w_prior
    from ..render import Renderer
    from ..shape.facemesh_topology import read_facemesh_topology
    from ..shape.model import load_shape_model

    root = ensure_models(["blazeface_short", "blazeface_full", "facemesh", "dlib_resnet", "facenet", "shape_model"])
    G = load_generator(root)
    sm = load_shape_model(root)
    m = FitModels(root, G, sm, load_dlib_resnet(root), load_w_prior(root, G), read_facemesh_topology(),
                  Renderer.for_shape_model(sm))
    m._g_state = {k: v.detach().clone() for k, v in G.state_dict().items()}
    return m


@dataclass(frozen=True)
class FitMetrics:
    """One fit's accuracy (see ``METRICS``; NaN where not measured) and cost."""

    landmark_px: float
    shape_mm: float
    shape_posed_mm: float
    albedo_l1: float
    albedo_delta_e: float
    albedo_delta_e_gain: float
    normals_deg: float
    identity_sim: float
    photometric: float
    fit_s: float  # detect + prepare + invert + tune, this process, wall clock
    iterations: int


@dataclass
class FitOutcome:
    metrics: FitMetrics
    inversion: object  # InversionResult
    maps: object  # the final ReflectanceMaps (after tuning)
    history: list[dict[str, float]]  # inversion then tuning losses
    tune_history: list[dict[str, float]]
    prepared: list  # PhotoInput per photo
    renders: np.ndarray  # (P, S, S, 3) uint8 the final render over each crop


def fit_photos(photos: list[np.ndarray], models: FitModels, s: FitSettings = FitSettings(),
               focal_35mm: float | None = None, truth=None, detect_score: float = 0.5) -> FitOutcome:
    """Fit ``photos`` ((H, W, 3) uint8 RGB, one person) and measure the result. ``truth``: a subject
    with ``n_views``, ``ibug68``, ``neutral``, ``vertices``, ``maps`` (``SyntheticSubject`` or
    ``bench.dataset.GroundTruth``) seen in the same photos, or None. ``detect_score``: BlazeFace's
    score threshold (``DetectSettings.score_threshold``). Raises NoFaceFound (the first photo without
    a face) as ``fitme fit`` would for a single photo."""
    import torch

    from ..fitting.invert import InversionSettings, TuningSettings, invert, prepare_photo, tune
    from ..fitting.metrics import evaluate_fit, landmark_error_px
    from ..fitting.skin_mask import photo_skin_mask
    from ..perception.detect import DetectSettings, detect
    from ..perception.facenet import facenet_embedding_onnx
    from ..reflectance.maps import ReflectanceMaps
    from ..render.camera import project
    from ..shape.regions import region_masks

    if not photos:
        raise ValueError("fit_photos: expected at least one photo, got none")
    if truth is not None and truth.n_views != len(photos):
        raise ValueError(f"fit_photos: {len(photos)} photos but the ground truth has {truth.n_views} views")
    sm, topo, G = models.shape_model, models.topology, models.G
    size = s.render_size
    t0 = time.perf_counter()
    prepared = []
    for photo in photos:
        lm = detect(photo, DetectSettings(identity=False, score_threshold=detect_score)).face.landmarks  # NoFaceFound propagates
        prepared.append(prepare_photo(photo, lm.points[:, :2], lm.ibug68, focal_35mm, size, 1.6,
                                      lambda c, pts: photo_skin_mask(c, pts, topo.triangles, topo.contours)))
    jaw = np.unique(topo.contours["face_oval"])
    inv_s = InversionSettings(iterations=s.iterations, render_size=size, coarse_fraction=s.coarse_fraction,
                              coarse_resolution=s.coarse_resolution, select_effects=s.select_effects,
                              forced_effects=s.forced_effects, seed=s.seed,
                              start_jitter=s.start_jitter)
    inv = invert(prepared, G, sm, models.descriptor, sm.landmarks, jaw, inv_s, prior=models.prior)
    maps, tune_hist = inv.maps, []
    if s.tune_iterations:
        mapped = torch.from_numpy(region_masks(sm.region_uv.cpu().numpy().astype(np.uint8), G.settings.resolution)["mapped"])
        try:
            tr = tune(prepared, G, inv, sm, models.descriptor, sm.landmarks, jaw, mapped,
                      TuningSettings(iterations=s.tune_iterations))
        finally:
            models.restore_generator()
        maps, tune_hist = tr.maps, tr.history
    fit_s = time.perf_counter() - t0

    n = len(prepared)
    with torch.no_grad():
        shp = sm(inv.p_s.expand(n, -1), inv.p_e)
        photo = torch.stack([torch.from_numpy(p.crop).permute(2, 0, 1).float() / 255 for p in prepared])
        from ..render.shading import srgb_to_linear

        out = models.renderer(shp.vertices, shp.normals, shp.tangents, ReflectanceMaps(maps.albedo, maps.specular, maps.normals),
                              inv.cameras, inv.lights, inv.effects, background=srgb_to_linear(photo))
        fitted68 = project(shp.vertices[:, sm.ibug68], inv.cameras)[..., :2].numpy()
        skin = torch.stack([torch.from_numpy(p.skin) for p in prepared])[:, None] * (out.mask > 0.5)
        diff = ((out.image.clamp(0, 1) - photo).abs() * skin).sum() / (3 * skin.sum()).clamp(min=1)
    renders = (out.image.clamp(0, 1).permute(0, 2, 3, 1).numpy() * 255 + 0.5).astype(np.uint8)
    sims = [float(np.dot(facenet_embedding_onnx(p.crop, p.ibug68, models.root),
                         facenet_embedding_onnx(r, p.ibug68, models.root)))  # the render sits where the face was
            for p, r in zip(prepared, renders)]
    nan = float("nan")
    if truth is not None:
        rep = evaluate_fit(truth, sm, inv.p_s, inv.p_e, inv.cameras, maps, [p.to_photo for p in prepared])
        acc = dict(landmark_px=rep.landmark_px, shape_mm=rep.shape.mean_mm, shape_posed_mm=rep.shape_posed_mean_mm,
                   albedo_l1=rep.albedo.l1_linear, albedo_delta_e=rep.albedo.delta_e,
                   albedo_delta_e_gain=rep.albedo.delta_e_gain, normals_deg=rep.normals_deg)
    else:  # no truth: the fit's landmarks against the detector's, in photo pixels
        to_ph = [lambda x, a=p.to_photo: x @ a[:, :2].T + a[:, 2] for p in prepared]
        lm = float(np.mean([landmark_error_px(f(fitted68[i]), f(p.ibug68)) for i, (f, p) in enumerate(zip(to_ph, prepared))]))
        acc = dict(landmark_px=lm, shape_mm=nan, shape_posed_mm=nan, albedo_l1=nan, albedo_delta_e=nan,
                   albedo_delta_e_gain=nan, normals_deg=nan)
    metrics = FitMetrics(**acc, identity_sim=float(np.mean(sims)), photometric=255 * float(diff), fit_s=fit_s,
                         iterations=s.iterations)
    return FitOutcome(metrics, inv, maps, inv.history + tune_hist, tune_hist, prepared, renders)
