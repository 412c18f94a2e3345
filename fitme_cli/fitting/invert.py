"""GAN inversion (FitMe Sec. 3.4.1): W, shape, expressions, cameras and lights, fitted together through
the renderer to one or several photos of one person. Photos share W and p_s; each has its own camera,
lights and expression.

Then tuning (Sec. 3.4.2): W frozen, only the generator's 4 middle synthesis layers train, against the
perceptual, photometric, flip and chromaticity losses.

The effect selector runs once, after ``select_fraction`` of the iterations: it measures the
photometric residual of the fit so far with the base effects and with each optional effect (a second
light and an SH environment fitted for a few steps with everything else frozen; shadows as they are)
and keeps an effect only where it lowers the residual by the selector's threshold
(``render.effects.select_effects``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import cv2
import numpy as np
import torch

from ..reflectance.gan.networks import Generator, decode_maps
from ..reflectance.maps import ReflectanceMaps
from ..render import Camera, Effects, Lights, Renderer
from ..render.effects import EffectChoice, SelectorSettings, select_effects
from ..render.camera import focal_px_from_35mm, project
from ..render.lights import single_colour_sh
from ..render.shading import srgb_to_linear
from ..shape.regions import REGIONS
from .losses import identity_loss, landmark_loss, mean_colour_loss, perceptual_loss, photometric_loss, w_prior
from .pose import initial_camera

__all__ = ["InversionSettings", "TuningSettings", "member_settings", "PhotoInput", "InversionResult", "TuningResult",
           "prepare_photo", "invert", "tune"]


@dataclass(frozen=True)
class InversionSettings:
    iterations: int = 200  # the paper: 200 (main text) to 250 (supplementary)
    lr: float = 1e-2  # the paper's l_inv
    render_size: int = 256  # the paper renders 512^2; 256^2 is our CPU default
    crop_scale: float = 1.6  # crop side / landmark bounding-box side
    # the paper's lambda_1..7: landmarks, photometric, identity, perceptual, W, shape, expression; lambda_4
    # is 25 / 25: our perceptual distance (dlib ResNet activations, unit-normalised per position, squared
    # differences summed over channels) is ~25x an LPIPS value for the same pair of faces
    lambdas: tuple[float, float, float, float, float, float, float] = (100.0, 0.5, 1.0, 1.0, 5e-2, 5e-4, 5e-4)
    jaw_weight: float = 0.3  # landmarks on the face outline slide along it: trust them less
    # not in the paper: the hair term, the mean colour of the rendered scalp against the photo's there
    # (_Problem.evaluate), at the photometric lambda_2. The paper's L_ph covers the whole render; ours
    # covers the photo's skin, so nothing saw the hair and a fit kept its w_avg start's. From the 154 kimg
    # G on that is grey: the fast preset gave the camera man grey hair, and darkening its scalp alone
    # lifted FaceNet similarity 0.135 -> 0.32 (docs/fitting.md "The hair term")
    hair_weight: float = 0.5
    # share of iterations with the synthesis stopped at coarse_resolution. Off by default: the 92 kimg
    # generator's 256^2 branch blocks change the colours, not only the detail (stopped at 128^2 its
    # albedo's red channel is 0.23 higher in network space), so W fitted on coarse maps lands the albedo
    # at half its brightness (docs/fitting.md, "Coarse-to-fine")
    coarse_fraction: float = 0.0
    coarse_resolution: int = 128  # 64 jumps at the switch even with the 35 kimg model
    # the paper optimises W, one w for every layer; W+ (a w per layer) fits the photo more closely but
    # leaves the generator's distribution: noisy, striped albedo with the light baked in (paper Fig. 9d)
    w_plus: bool = False
    # L_W: "pnorm", the whitened distance in the mapping's pre-activation space (reflectance/gan/
    # latent_prior.py; ~1 for a typical sample), or "paper", the mean squared distance to w_avg
    w_prior: str = "pnorm"
    effects: Effects = field(default_factory=Effects)  # the effects when ``select_effects`` is off
    select_effects: bool = True  # choose the effects from the photos and the fit so far
    # not in the paper: the SH environment in one colour (``render.lights.single_colour_sh``); free, it
    # lit the sides green and the underside magenta, where the skin mask does not reach
    sh_one_colour: bool = True
    select_fraction: float = 0.4  # the selector runs after this share of the iterations
    forced_effects: tuple[tuple[str, bool], ...] = ()  # user overrides, (name, on) pairs; always win
    selection_steps: int = 8  # Adam steps that fit a candidate second light or SH environment
    selector: SelectorSettings = field(default_factory=SelectorSettings)
    # the generator's fixed noise maps at this share of their trained strength. They are nobody's grain:
    # W cannot steer them, and at full strength the 92 kimg model's grain and low-frequency ripples stay
    # in every fit. Measured on the three sample photos (FaceNet similarity of photo and render,
    # docs/fitting.md "Noise gain"): default preset 0.513 at 1, 0.570 at 0.35, 0.541 at 0.
    noise_gain: float = 0.35
    seed: int = 0
    # std of a seeded Gaussian added to the starting w (0: start at w_avg, the paper). A fit is chaotic:
    # a 1e-5 nudge spreads its result as far as another CPU's float rounding does, so the regression
    # run fits each case from several nudged starts and compares medians (bench/regress.py)
    start_jitter: float = 0.0

    def __post_init__(self) -> None:
        if not (self.start_jitter >= 0.0 and math.isfinite(self.start_jitter)):
            raise ValueError(f"InversionSettings.start_jitter must be finite and >= 0, got {self.start_jitter}")
        if not 0.0 <= self.noise_gain <= 1.0:
            raise ValueError(f"InversionSettings.noise_gain must be in [0, 1], got {self.noise_gain}")
        if not (self.hair_weight >= 0.0 and math.isfinite(self.hair_weight)):
            raise ValueError(f"InversionSettings.hair_weight must be finite and >= 0, got {self.hair_weight}")
        for name in ("coarse_fraction", "select_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"InversionSettings.{name} must be in [0, 1], got {getattr(self, name)}")


def member_settings(s, m: int, jitter: float):
    """The m-th member of an ensemble of fits of one photo set: member 0 is ``s`` itself, member m > 0
    is ``s`` seeded by m and started from w_avg nudged by ``jitter`` (``start_jitter``): the spread that
    another CPU's float rounding gives a fit, on one machine. ``s``: any frozen settings dataclass with
    ``seed`` and ``start_jitter`` fields (``InversionSettings``, ``bench.run.FitSettings``)."""
    if m < 0:
        raise ValueError(f"member_settings: m must be >= 0, got {m}")
    return s if m == 0 else replace(s, seed=m, start_jitter=jitter)


@dataclass(frozen=True)
class TuningSettings:
    iterations: int = 20  # the paper: 20 (main text) to 30 (supplementary)
    lr: float = 8e-4  # the paper's l_pti
    layers: int = 4  # the middle synthesis layers that train
    # the paper's lambda_8..11: perceptual (LPIPS there, dlib activations here: rescaled by 1/25 as
    # lambda_4), photometric, flip, chromaticity
    lambdas: tuple[float, float, float, float] = (2.0 / 25, 0.5, 0.8, 0.35)
    hair_weight: float = 0.5  # not in the paper: the inversion's hair term (InversionSettings.hair_weight)
    effects: Effects | None = None  # None: the effects the inversion chose

    def __post_init__(self) -> None:
        if not (self.hair_weight >= 0.0 and math.isfinite(self.hair_weight)):
            raise ValueError(f"TuningSettings.hair_weight must be finite and >= 0, got {self.hair_weight}")


@dataclass(frozen=True)
class PhotoInput:
    """One photo prepared for fitting: a square crop around the face at the render size.

    crop: (S, S, 3) uint8 sRGB; landmarks: (468, 2) and ibug68: (68, 2) crop pixels; skin: (S, S) float32
    {0, 1}; focal_px: focal length in crop pixels; principal: (2,) the photo's centre in crop pixels;
    to_photo: (2, 3) affine crop px -> photo px."""

    crop: np.ndarray
    landmarks: np.ndarray
    ibug68: np.ndarray
    skin: np.ndarray
    focal_px: float
    principal: np.ndarray
    to_photo: np.ndarray


@dataclass(frozen=True)
class InversionResult:
    ws: torch.Tensor  # (1, num_ws, w_dim)
    p_s: torch.Tensor  # (1, K)
    p_e: torch.Tensor  # (P, E)
    cameras: Camera  # batch P, crop pixels
    lights: Lights  # batch P
    maps: ReflectanceMaps  # (1, ., R, R) physical maps at the generator's resolution
    history: list[dict[str, float]]  # per iteration: total and each weighted loss (mean over photos)
    effects: Effects  # the effects of the fine phase (and of the final render)
    choice: EffectChoice | None  # the selector's decision and reasons; None when not selected
    coarse_residuals: dict[str, float]  # photometric residual of the fit at the selection per candidate effect
    # (the name is from when the selector ran at the end of the coarse phase; avatar.json keeps it)
    noise_gain: float = 1.0  # the generator's noise gain the maps were made with (tuning keeps it)
    selected_at: int | None = None  # the iteration the effect selector ran at; None: it did not run


@dataclass(frozen=True)
class TuningResult:
    layers: dict[str, torch.Tensor]  # the tuned parameters of the middle layers (state-dict names)
    maps: ReflectanceMaps  # (1, ., R, R) after tuning
    history: list[dict[str, float]]


def prepare_photo(rgb: np.ndarray, landmarks: np.ndarray, ibug68: np.ndarray, focal_35mm: float | None,
                  size: int, crop_scale: float, skin_mask_fn) -> PhotoInput:
    """Crop the face to ``size``^2 and carry the landmarks, the skin mask and the intrinsics along."""
    h, w = rgb.shape[:2]
    lo, hi = landmarks.min(0), landmarks.max(0)
    centre = (lo + hi) / 2
    side = crop_scale * float(max(hi - lo))
    s = size / side
    a = np.array([[s, 0, size / 2 - s * centre[0]], [0, s, size / 2 - s * centre[1]]])  # photo -> crop
    crop = cv2.warpAffine(rgb, a, (size, size), flags=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
    lm = landmarks @ a[:, :2].T + a[:, 2]
    i68 = ibug68 @ a[:, :2].T + a[:, 2]
    inv = np.array([[1 / s, 0, centre[0] - size / 2 / s], [0, 1 / s, centre[1] - size / 2 / s]])
    return PhotoInput(crop, lm.astype(np.float32), i68.astype(np.float32), skin_mask_fn(crop, lm),
                      focal_px_from_35mm(focal_35mm, w, h) * s, np.array([w / 2, h / 2]) @ a[:, :2].T + a[:, 2], inv)


def _rodrigues(aa: torch.Tensor) -> torch.Tensor:
    """(P, 3) axis-angle -> (P, 3, 3), smooth at 0."""
    theta2 = aa.square().sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-12)
    k = aa / theta
    kx, ky, kz = k.unbind(-1)
    z = torch.zeros_like(kx)
    kmat = torch.stack([z, -kz, ky, kz, z, -kx, -ky, kx, z], -1).view(-1, 3, 3)
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(kmat)
    return eye + s * kmat + (1 - c) * kmat @ kmat


def _detached(obj):
    """A copy of a frozen dataclass of tensors (``Camera``, ``Lights``) with every tensor cut from the graph."""
    return replace(obj, **{f.name: getattr(obj, f.name).detach() for f in fields(obj) if isinstance(getattr(obj, f.name), torch.Tensor)})


# the hair term skips the silhouette's last pixels: antialiasing blends them with the photo behind,
# and hair reaches past the skull, so there the render's scalp meets the background, not the hair
_HAIR_MARGIN = 2


class _Problem:
    """The photos as tensors, and one differentiable evaluation of the scene against them."""

    def __init__(self, photos: list[PhotoInput], shape_model, descriptor, landmark_vertices: torch.Tensor,
                 jaw: np.ndarray, jaw_weight: float, size: int, device: torch.device | str = "cpu"):
        from ..perception.face_chip import extract_chip_torch, face_chip_affine

        dev = torch.device(device)
        self.n, self.size, self.device = len(photos), size, dev
        self.shape_model, self.descriptor, self.landmark_vertices = shape_model, descriptor, landmark_vertices
        self.renderer = Renderer.for_shape_model(shape_model).to(dev)
        self.photo = torch.stack([torch.from_numpy(p.crop).permute(2, 0, 1).float() / 255 for p in photos]).to(dev)  # sRGB
        self.photo_lin = srgb_to_linear(self.photo)
        self.skin = torch.stack([torch.from_numpy(p.skin) for p in photos])[:, None].to(dev)
        # (F,) bool, triangles with every corner on the scalp: where the render shows the hair
        self.scalp_triangle = (shape_model.regions[shape_model.triangles] == REGIONS.index("scalp")).all(-1).to(dev)
        self.target_lm = torch.stack([torch.from_numpy(p.landmarks) for p in photos]).to(dev)
        self.face_size = torch.tensor([float(np.ptp(p.landmarks, 0).max()) for p in photos], device=dev)
        self.lm_w = torch.ones(468, device=dev)
        self.lm_w[torch.as_tensor(jaw, device=dev)] = jaw_weight
        self.chip_affine = torch.stack([torch.from_numpy(face_chip_affine(p.ibug68.astype(np.float64))).float()
                                        for p in photos]).to(dev)
        self._chip = extract_chip_torch
        with torch.no_grad():
            self.photo_feats = descriptor.features(extract_chip_torch(self.photo, self.chip_affine))
        mean_lm = shape_model.mean[landmark_vertices].detach().cpu().numpy()
        cams = [initial_camera(p.landmarks, mean_lm, size, size, p.focal_px, principal=p.principal) for p in photos]
        self.rot0 = torch.cat([c.rotation for c in cams]).to(dev)
        self.focal = torch.cat([c.focal for c in cams]).to(dev)
        self.principal = torch.cat([c.principal for c in cams]).to(dev)
        self.trans0 = torch.cat([c.translation for c in cams]).to(dev)

    def camera(self, aa: torch.Tensor, trans: torch.Tensor) -> Camera:
        return Camera(self.focal, self.principal, _rodrigues(aa) @ self.rot0, trans, self.size, self.size)

    def residual(self, maps: ReflectanceMaps, p_s, p_e, cam: Camera, lights: Lights, effects: Effects) -> torch.Tensor:
        """(P,) photometric residual of one render (the effect selector's measure)."""
        shp = self.shape_model(p_s.expand(self.n, -1), p_e)
        out = self.renderer(shp.vertices, shp.normals, shp.tangents, maps, cam, lights, effects, background=self.photo_lin)
        return photometric_loss(out.image, self.photo, self.skin * out.mask)

    def hair_mask(self, triangle: torch.Tensor) -> torch.Tensor:
        """(P, 1, S, S) float, 1 where the render shows a scalp triangle outside the photo's skin mask and
        at least ``_HAIR_MARGIN`` pixels inside the silhouette. triangle: (P, S, S) int64 rasterised
        triangle index, -1 on the background (``Fragments.triangle``)."""
        scalp = (self.scalp_triangle[triangle.clamp(min=0)] & (triangle >= 0))[:, None].to(self.skin.dtype)
        k = 2 * _HAIR_MARGIN + 1
        near_background = torch.nn.functional.max_pool2d((triangle < 0)[:, None].to(scalp.dtype), k, 1, _HAIR_MARGIN)
        return scalp * (1 - near_background) * (1 - self.skin)

    def evaluate(self, maps: ReflectanceMaps, p_s, p_e, cam: Camera, lights: Lights, effects: Effects,
                 with_landmarks: bool = True, with_identity: bool = True, with_hair: bool = True) -> dict[str, torch.Tensor]:
        """Unweighted (P,) losses of one render of the scene."""
        shp = self.shape_model(p_s.expand(self.n, -1), p_e)
        out = self.renderer(shp.vertices, shp.normals, shp.tangents, maps, cam, lights, effects, background=self.photo_lin)
        terms = {"photometric": photometric_loss(out.image, self.photo, self.skin * out.mask)}
        if with_hair:
            # W alone answers the hair term: in its own render the geometry, camera and lights are cut
            # from the graph. Through the shared render it moved the head, so that Grace Hopper's cap fell
            # outside the scalp, and doubled her landmark error (fast preset: 5.8 -> 14 px)
            hair = self.renderer(shp.vertices.detach(), shp.normals.detach(), shp.tangents.detach(), maps, _detached(cam),
                                 _detached(lights), effects, background=self.photo_lin).image
            mask = self.hair_mask(out.fragments.triangle)
            # weighted by the hair's share of the pixels the two terms see (the paper's L_ph covers the
            # whole render): a glimpse of scalp under a cap weighs little, a profile's back of the head much
            area = mask.sum(dim=(1, 2, 3))
            share = area / (area + (self.skin * out.mask).sum(dim=(1, 2, 3))).clamp(min=1.0)
            terms["hair"] = share * mean_colour_loss(hair, self.photo, mask)
        if with_landmarks:
            lm = project(shp.vertices[:, self.landmark_vertices], cam)[..., :2]
            terms["landmarks"] = landmark_loss(lm, self.target_lm, self.lm_w, self.face_size)
        feats = self.descriptor.features(self._chip(out.image, self.chip_affine))
        if with_identity:
            terms["identity"] = identity_loss(feats.descriptor, self.photo_feats.descriptor)
        terms["perceptual"] = perceptual_loss(feats.activations, self.photo_feats.activations)
        return terms


def _check_finite(total: torch.Tensor, terms: dict[str, torch.Tensor], it: int) -> None:
    """Stop at the first non-finite loss, naming the terms: Adam would otherwise spread NaN everywhere."""
    if not torch.isfinite(total):
        bad = {k: float(v.detach().mean()) for k, v in terms.items()}
        raise FloatingPointError(f"non-finite loss at iteration {it}: {bad}")


def _sh_from_ambient(ambient: torch.Tensor) -> torch.Tensor:
    """(P, 3) constant ambient -> (P, 9, 3) SH irradiance coefficients of the same light (Y_00 only)."""
    sh = torch.zeros(ambient.shape[0], 9, 3, dtype=ambient.dtype, device=ambient.device)
    sh[:, 0] = ambient * 2 * float(np.sqrt(np.pi))
    return sh


def _base_effects(s: InversionSettings) -> Effects:
    forced = dict(s.forced_effects)
    if not s.select_effects:
        return replace(s.effects, **forced)
    base = replace(s.effects, multi_light=False, sh_ambient=False, shadows=False)
    return replace(base, **{k: v for k, v in forced.items() if k in ("specular", "subsurface")})


def _fit_candidate(pb: _Problem, maps, p_s, p_e, cam, make_lights, params, effects: Effects, steps: int) -> float:
    """Fit ``params`` (lights only) for a few steps with the rest frozen; the residual after."""
    opt = torch.optim.Adam(params, lr=0.05)
    for _ in range(steps):
        loss = pb.residual(maps, p_s, p_e, cam, make_lights(), effects).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        return float(pb.residual(maps, p_s, p_e, cam, make_lights(), effects).mean())


def invert(photos: list[PhotoInput], G: Generator, shape_model, descriptor, landmark_vertices: torch.Tensor,
           jaw: np.ndarray, s: InversionSettings = InversionSettings(), progress=None,
           device: torch.device | str = "cpu", prior=None) -> InversionResult:
    """Fit the photos of one person. ``descriptor``: the dlib ResNet torch twin (identity and perceptual
    losses); ``landmark_vertices``: (468,) mesh vertex of each FaceMesh landmark; ``jaw``: landmark
    indices on the face outline. ``progress(i, total, losses)`` is called every iteration. G, the shape
    model and the descriptor must already be on ``device``. ``prior``: the generator's ``WPrior``
    (``gan.store.load_w_prior`` caches it); None fits it here (0.8 s)."""
    torch.manual_seed(s.seed)
    dev = torch.device(device)
    pb = _Problem(photos, shape_model, descriptor, landmark_vertices, jaw, s.jaw_weight, s.render_size, dev)
    n = pb.n
    w0 = G.w_avg.detach().clone().view(1, 1, -1)
    if s.start_jitter > 0:
        gen = torch.Generator().manual_seed(s.seed)
        w0 = w0 + s.start_jitter * torch.randn(w0.shape, generator=gen).to(w0)
    w_var = (w0.repeat(1, G.settings.num_ws, 1) if s.w_plus else w0).requires_grad_(True)

    def all_ws():
        return w_var if s.w_plus else w_var.expand(1, G.settings.num_ws, -1)
    # p_s is optimised in standard deviations: its raw units (mm along unit basis vectors) have
    # sigma 60-340, so the paper's lr would move a coefficient < 1 mm over a whole fit
    s_std = shape_model.identity_eigenvalues.sqrt().to(dev)
    z_s = torch.zeros(1, shape_model.n_identity, requires_grad=True, device=dev)

    def shape_coeffs():
        return z_s * s_std
    p_e = torch.zeros(n, shape_model.n_expressions, requires_grad=True, device=dev)
    aa = torch.zeros(n, 3, requires_grad=True, device=dev)
    trans = pb.trans0.clone().requires_grad_(True)
    eye_dir = torch.einsum("pji,pj->pi", pb.rot0, -pb.trans0)  # camera centre in world: a frontal key light
    light_dir = torch.nn.functional.normalize(eye_dir, dim=-1).clone().requires_grad_(True)
    ambient = torch.full((n, 3), 0.5, requires_grad=True, device=dev)
    colour = torch.full((n, 3), 0.5, requires_grad=True, device=dev)
    extra: dict[str, torch.Tensor] = {}  # the selected second light ("dir2", "colour2") and SH environment ("sh")
    params = [w_var, z_s, p_e, aa, light_dir, ambient, colour]
    # translation is in mm: the paper's lr (for unit-scale parameters) would move it 0.01 mm a step
    opt = torch.optim.Adam([{"params": params}, {"params": [trans], "lr": s.lr * 100}], lr=s.lr)
    lam = dict(zip(("landmarks", "photometric", "identity", "perceptual", "w", "shape", "expression"), s.lambdas))
    lam["hair"] = s.hair_weight
    history: list[dict[str, float]] = []
    n_coarse = int(s.coarse_fraction * s.iterations)
    r_full = G.settings.resolution
    if s.w_prior == "pnorm":
        if prior is None:
            from ..reflectance.gan.latent_prior import fit_w_prior

            prior = fit_w_prior(G.mapping, G.settings.z_dim)
        prior = prior.to(dev)

        def w_loss(ws):
            return prior.distance(ws)
    elif s.w_prior == "paper":
        def w_loss(ws):
            return w_prior(ws, G.w_avg)
    else:
        raise ValueError(f"w_prior must be 'pnorm' or 'paper', got {s.w_prior!r}")
    effects = _base_effects(s)
    choice, residuals = None, {}
    select_at = max(1, int(s.select_fraction * s.iterations)) if s.select_effects and s.iterations > 1 else -1
    if effects.sh_ambient or effects.multi_light:  # forced without the selector: their lights must exist
        new = []
        if effects.sh_ambient:
            extra["sh"] = _sh_from_ambient(ambient.detach()).requires_grad_(True)
            new.append(extra["sh"])
        if effects.multi_light:  # a fill light from the camera's left
            fill = torch.nn.functional.normalize(light_dir.detach() - 1.5 * pb.rot0[:, 0, :], dim=-1)
            extra["dir2"] = fill.clone().requires_grad_(True)
            extra["colour2"] = torch.full((n, 3), 0.3, device=dev, requires_grad=True)
            new += [extra["dir2"], extra["colour2"]]
        opt.add_param_group({"params": new, "lr": s.lr})

    def lights_now(d2=None, c2=None, sh=None):
        d2, c2, sh = d2 if d2 is not None else extra.get("dir2"), c2 if c2 is not None else extra.get("colour2"), sh if sh is not None else extra.get("sh")
        dirs, cols = light_dir[:, None], colour.clamp(min=0)[:, None]
        if d2 is not None:
            dirs = torch.cat([dirs, torch.nn.functional.normalize(d2, dim=-1)[:, None]], 1)
            cols = torch.cat([cols, c2.clamp(min=0)[:, None]], 1)
        if sh is not None and s.sh_one_colour:
            sh = single_colour_sh(sh)
        return Lights(ambient.clamp(min=0), dirs, cols, sh=sh)

    def select(maps):
        nonlocal choice, residuals, effects
        frozen = [shape_coeffs().detach(), p_e.detach()]
        cam = pb.camera(aa.detach(), trans.detach())
        mp = ReflectanceMaps(*(t.detach() for t in (maps.albedo, maps.specular, maps.normals)))
        with torch.no_grad():
            residuals = {"base": float(pb.residual(mp, *frozen, cam, lights_now(), effects).mean()),
                         "shadows": float(pb.residual(mp, *frozen, cam, lights_now(), replace(effects, shadows=True)).mean())}
            key = light_dir.detach()
        # a second light from the camera's left or right, 56 degrees off the key light: start from the better side
        right = pb.rot0[:, 0, :]  # the camera's x axis in the world frame
        c2 = torch.full((n, 3), 0.3, device=dev)
        with torch.no_grad():
            sides = [torch.nn.functional.normalize(key + k * 1.5 * right, dim=-1) for k in (-1.0, 1.0)]
            r_side = [float(pb.residual(mp, *frozen, cam, lights_now(d2=d, c2=c2), replace(effects, multi_light=True)).mean())
                      for d in sides]
        d2 = sides[int(np.argmin(r_side))].clone().requires_grad_(True)
        c2 = c2.requires_grad_(True)
        residuals["multi_light"] = _fit_candidate(pb, mp, *frozen, cam, lambda: lights_now(d2=d2, c2=c2), [d2, c2],
                                                  replace(effects, multi_light=True), s.selection_steps)
        sh = _sh_from_ambient(ambient.detach()).requires_grad_(True)
        residuals["sh_ambient"] = _fit_candidate(pb, mp, *frozen, cam, lambda: lights_now(sh=sh), [sh],
                                                 replace(effects, sh_ambient=True), s.selection_steps)
        face_px = float(np.median([np.ptp(p.landmarks[:, 0]) * abs(p.to_photo[0, 0]) for p in photos]))
        skin = np.concatenate([p.crop[p.skin > 0.5] for p in photos]).astype(np.float64) / 255
        choice = select_effects(face_px, skin, residuals, dict(s.forced_effects), s.selector)
        effects = choice.effects
        new = []
        if effects.multi_light:
            extra["dir2"], extra["colour2"] = d2.detach().clone().requires_grad_(True), c2.detach().clone().requires_grad_(True)
            new += [extra["dir2"], extra["colour2"]]
        if effects.sh_ambient:
            extra["sh"] = sh.detach().clone().requires_grad_(True)
            new.append(extra["sh"])
        if new:
            opt.add_param_group({"params": new, "lr": s.lr})

    for it in range(s.iterations):
        res = s.coarse_resolution if it < n_coarse and s.coarse_resolution < r_full else None
        ws = all_ws()
        maps = decode_maps(G.synthesis(ws, noise_mode="const", max_resolution=res, noise_gain=s.noise_gain), G.settings)
        if it == select_at:
            select(maps)
        p_s = shape_coeffs()
        terms = pb.evaluate(maps, p_s, p_e, pb.camera(aa, trans), lights_now(), effects, with_hair=s.hair_weight > 0)
        terms["w"] = w_loss(ws).expand(n)
        terms["shape"] = shape_model.identity_prior(p_s).expand(n)
        terms["expression"] = shape_model.expression_prior(p_e)
        weighted = {k: lam[k] * v for k, v in terms.items()}
        total = sum(t.mean() for t in weighted.values())
        _check_finite(total, weighted, it)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        with torch.no_grad():
            light_dir.copy_(torch.nn.functional.normalize(light_dir, dim=-1))
        rec = {"total": float(total.detach())} | {k: float(v.detach().mean()) for k, v in weighted.items()}
        history.append(rec)
        if progress is not None:
            progress(it, s.iterations, rec)
    with torch.no_grad():
        ws = all_ws().contiguous()
        maps = decode_maps(G.synthesis(ws, noise_mode="const", noise_gain=s.noise_gain), G.settings)
        cam = pb.camera(aa, trans)
        lights = lights_now()
    cam, lights = _detached(cam), _detached(lights)
    return InversionResult(ws.detach(), shape_coeffs().detach(), p_e.detach(), cam, lights, maps, history, effects, choice,
                           residuals, s.noise_gain, select_at if choice is not None else None)


def tune(photos: list[PhotoInput], G: Generator, inv: InversionResult, shape_model, descriptor,
         landmark_vertices: torch.Tensor, jaw: np.ndarray, mapped: torch.Tensor,
         s: TuningSettings = TuningSettings(), render_size: int | None = None, progress=None,
         device: torch.device | str = "cpu") -> TuningResult:
    """Train the generator's middle layers with W (and shape, cameras, lights) frozen at the inversion's
    values. ``mapped``: (R, R) bool UV texels on the mesh (for the flip and chromaticity losses). G is
    modified in place (its tuned layers); the result also carries their new values."""
    from .losses import chromaticity_loss, flip_loss

    pb = _Problem(photos, shape_model, descriptor, landmark_vertices, jaw, 1.0, render_size or inv.cameras.width, device)
    middle = G.synthesis.middle_layers(s.layers)
    params = [p for name in middle for p in G.synthesis.layer_parameters(name)]
    G.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=s.lr)
    lam = dict(zip(("perceptual", "photometric", "flip", "chromaticity"), s.lambdas))
    lam["hair"] = s.hair_weight
    reference = inv.maps.albedo.detach()
    history: list[dict[str, float]] = []
    for it in range(s.iterations):
        maps = decode_maps(G.synthesis(inv.ws, noise_mode="const", noise_gain=inv.noise_gain), G.settings)
        terms = pb.evaluate(maps, inv.p_s, inv.p_e, inv.cameras, inv.lights, s.effects or inv.effects, with_landmarks=False,
                            with_identity=False, with_hair=s.hair_weight > 0)
        terms["flip"] = flip_loss(maps.albedo, mapped.to(pb.device)).expand(pb.n)
        terms["chromaticity"] = chromaticity_loss(maps.albedo, reference, mapped.to(pb.device)).expand(pb.n)
        weighted = {k: lam[k] * v for k, v in terms.items()}
        total = sum(t.mean() for t in weighted.values())
        _check_finite(total, weighted, it)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        rec = {"total": float(total.detach())} | {k: float(v.detach().mean()) for k, v in weighted.items()}
        history.append(rec)
        if progress is not None:
            progress(it, s.iterations, rec)
    G.requires_grad_(False)
    trained = {id(p) for p in params}
    tuned = {k: v.detach().clone() for k, v in G.named_parameters() if id(v) in trained}
    with torch.no_grad():
        maps = decode_maps(G.synthesis(inv.ws, noise_mode="const", noise_gain=inv.noise_gain), G.settings)
    return TuningResult(tuned, maps, history)
