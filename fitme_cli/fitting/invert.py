"""GAN inversion (FitMe Sec. 3.4.1): W, shape, expressions, cameras and lights, fitted together through
the renderer to one or several photos of one person. Photos share W and p_s; each has its own camera,
lights and expression.

Then tuning (Sec. 3.4.2): W frozen, only the generator's 4 middle synthesis layers train, against the
perceptual, photometric, flip and chromaticity losses.

Status: both loops work (tests/test_fit_invert.py). Not yet: the effect selector's coarse-fit
residuals, presets and speed, the avatar directory and the CLI (issue 6).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..reflectance.gan.networks import Generator, decode_maps
from ..reflectance.maps import ReflectanceMaps
from ..render import Camera, Effects, Lights, Renderer
from ..render.camera import focal_px_from_35mm, project
from ..render.shading import srgb_to_linear
from .losses import identity_loss, landmark_loss, perceptual_loss, photometric_loss, w_prior
from .pose import initial_camera

__all__ = ["InversionSettings", "TuningSettings", "PhotoInput", "InversionResult", "TuningResult", "prepare_photo",
           "invert", "tune"]


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
    coarse_fraction: float = 0.4  # share of iterations with the synthesis stopped at coarse_resolution
    coarse_resolution: int = 64
    effects: Effects = field(default_factory=Effects)
    seed: int = 0


@dataclass(frozen=True)
class TuningSettings:
    iterations: int = 20  # the paper: 20 (main text) to 30 (supplementary)
    lr: float = 8e-4  # the paper's l_pti
    layers: int = 4  # the middle synthesis layers that train
    # the paper's lambda_8..11: perceptual (LPIPS there, dlib activations here: rescaled by 1/25 as
    # lambda_4), photometric, flip, chromaticity
    lambdas: tuple[float, float, float, float] = (2.0 / 25, 0.5, 0.8, 0.35)
    effects: Effects = field(default_factory=Effects)


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


class _Problem:
    """The photos as tensors, and one differentiable evaluation of the scene against them."""

    def __init__(self, photos: list[PhotoInput], shape_model, descriptor, landmark_vertices: torch.Tensor,
                 jaw: np.ndarray, jaw_weight: float, size: int):
        from ..perception.face_chip import extract_chip_torch, face_chip_affine

        self.n, self.size = len(photos), size
        self.shape_model, self.descriptor, self.landmark_vertices = shape_model, descriptor, landmark_vertices
        self.renderer = Renderer.for_shape_model(shape_model)
        self.photo = torch.stack([torch.from_numpy(p.crop).permute(2, 0, 1).float() / 255 for p in photos])  # sRGB
        self.photo_lin = srgb_to_linear(self.photo)
        self.skin = torch.stack([torch.from_numpy(p.skin) for p in photos])[:, None]
        self.target_lm = torch.stack([torch.from_numpy(p.landmarks) for p in photos])
        self.face_size = torch.tensor([float(np.ptp(p.landmarks, 0).max()) for p in photos])
        self.lm_w = torch.ones(468)
        self.lm_w[torch.as_tensor(jaw)] = jaw_weight
        self.chip_affine = torch.stack([torch.from_numpy(face_chip_affine(p.ibug68.astype(np.float64))).float() for p in photos])
        self._chip = extract_chip_torch
        with torch.no_grad():
            self.photo_feats = descriptor.features(extract_chip_torch(self.photo, self.chip_affine))
        mean_lm = shape_model.mean[landmark_vertices].detach().cpu().numpy()
        cams = [initial_camera(p.landmarks, mean_lm, size, size, p.focal_px, principal=p.principal) for p in photos]
        self.rot0 = torch.cat([c.rotation for c in cams])
        self.focal = torch.cat([c.focal for c in cams])
        self.principal = torch.cat([c.principal for c in cams])
        self.trans0 = torch.cat([c.translation for c in cams])

    def camera(self, aa: torch.Tensor, trans: torch.Tensor) -> Camera:
        return Camera(self.focal, self.principal, _rodrigues(aa) @ self.rot0, trans, self.size, self.size)

    def evaluate(self, maps: ReflectanceMaps, p_s, p_e, cam: Camera, lights: Lights, effects: Effects,
                 with_landmarks: bool = True, with_identity: bool = True) -> dict[str, torch.Tensor]:
        """Unweighted (P,) losses of one render of the scene."""
        shp = self.shape_model(p_s.expand(self.n, -1), p_e)
        out = self.renderer(shp.vertices, shp.normals, shp.tangents, maps, cam, lights, effects, background=self.photo_lin)
        terms = {"photometric": photometric_loss(out.image, self.photo, self.skin * out.mask)}
        if with_landmarks:
            lm = project(shp.vertices[:, self.landmark_vertices], cam)[..., :2]
            terms["landmarks"] = landmark_loss(lm, self.target_lm, self.lm_w, self.face_size)
        feats = self.descriptor.features(self._chip(out.image, self.chip_affine))
        if with_identity:
            terms["identity"] = identity_loss(feats.descriptor, self.photo_feats.descriptor)
        terms["perceptual"] = perceptual_loss(feats.activations, self.photo_feats.activations)
        return terms


def invert(photos: list[PhotoInput], G: Generator, shape_model, descriptor, landmark_vertices: torch.Tensor,
           jaw: np.ndarray, s: InversionSettings = InversionSettings(), progress=None) -> InversionResult:
    """Fit the photos of one person. ``descriptor``: the dlib ResNet torch twin (identity and perceptual
    losses); ``landmark_vertices``: (468,) mesh vertex of each FaceMesh landmark; ``jaw``: landmark
    indices on the face outline. ``progress(i, total, losses)`` is called every iteration."""
    torch.manual_seed(s.seed)
    pb = _Problem(photos, shape_model, descriptor, landmark_vertices, jaw, s.jaw_weight, s.render_size)
    n = pb.n
    ws = G.w_avg.detach().clone().view(1, 1, -1).repeat(1, G.settings.num_ws, 1).requires_grad_(True)
    p_s = torch.zeros(1, shape_model.n_identity, requires_grad=True)
    p_e = torch.zeros(n, shape_model.n_expressions, requires_grad=True)
    aa = torch.zeros(n, 3, requires_grad=True)
    trans = pb.trans0.clone().requires_grad_(True)
    eye_dir = torch.einsum("pji,pj->pi", pb.rot0, -pb.trans0)  # camera centre in world: a frontal key light
    light_dir = torch.nn.functional.normalize(eye_dir, dim=-1).clone().requires_grad_(True)
    ambient = torch.full((n, 3), 0.5, requires_grad=True)
    colour = torch.full((n, 3), 0.5, requires_grad=True)
    params = [ws, p_s, p_e, aa, light_dir, ambient, colour]
    # translation is in mm: the paper's lr (for unit-scale parameters) would move it 0.01 mm a step
    opt = torch.optim.Adam([{"params": params}, {"params": [trans], "lr": s.lr * 100}], lr=s.lr)
    lam = dict(zip(("landmarks", "photometric", "identity", "perceptual", "w", "shape", "expression"), s.lambdas))
    history: list[dict[str, float]] = []
    n_coarse = int(s.coarse_fraction * s.iterations)
    r_full = G.settings.resolution

    def lights_now():
        return Lights(ambient.clamp(min=0), light_dir[:, None], colour.clamp(min=0)[:, None])

    for it in range(s.iterations):
        res = s.coarse_resolution if it < n_coarse and s.coarse_resolution < r_full else None
        maps = decode_maps(G.synthesis(ws, noise_mode="const", max_resolution=res), G.settings)
        terms = pb.evaluate(maps, p_s, p_e, pb.camera(aa, trans), lights_now(), s.effects)
        terms["w"] = w_prior(ws, G.w_avg).expand(n)
        terms["shape"] = shape_model.identity_prior(p_s).expand(n)
        terms["expression"] = shape_model.expression_prior(p_e)
        weighted = {k: lam[k] * v for k, v in terms.items()}
        total = sum(t.mean() for t in weighted.values())
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
        maps = decode_maps(G.synthesis(ws, noise_mode="const"), G.settings)
        cam = pb.camera(aa, trans)
        lights = lights_now()
    cam = Camera(cam.focal.detach(), cam.principal.detach(), cam.rotation.detach(), cam.translation.detach(), pb.size, pb.size)
    lights = Lights(lights.ambient.detach(), lights.direction.detach(), lights.colour.detach())
    return InversionResult(ws.detach(), p_s.detach(), p_e.detach(), cam, lights, maps, history)


def tune(photos: list[PhotoInput], G: Generator, inv: InversionResult, shape_model, descriptor,
         landmark_vertices: torch.Tensor, jaw: np.ndarray, mapped: torch.Tensor,
         s: TuningSettings = TuningSettings(), render_size: int | None = None, progress=None) -> TuningResult:
    """Train the generator's middle layers with W (and shape, cameras, lights) frozen at the inversion's
    values. ``mapped``: (R, R) bool UV texels on the mesh (for the flip and chromaticity losses). G is
    modified in place (its tuned layers); the result also carries their new values."""
    from .losses import chromaticity_loss, flip_loss

    pb = _Problem(photos, shape_model, descriptor, landmark_vertices, jaw, 1.0, render_size or inv.cameras.width)
    middle = G.synthesis.middle_layers(s.layers)
    params = [p for name in middle for p in G.synthesis.layer_parameters(name)]
    G.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=s.lr)
    lam = dict(zip(("perceptual", "photometric", "flip", "chromaticity"), s.lambdas))
    reference = inv.maps.albedo.detach()
    history: list[dict[str, float]] = []
    for it in range(s.iterations):
        maps = decode_maps(G.synthesis(inv.ws, noise_mode="const"), G.settings)
        terms = pb.evaluate(maps, inv.p_s, inv.p_e, inv.cameras, inv.lights, s.effects, with_landmarks=False,
                            with_identity=False)
        terms["flip"] = flip_loss(maps.albedo, mapped).expand(pb.n)
        terms["chromaticity"] = chromaticity_loss(maps.albedo, reference, mapped).expand(pb.n)
        weighted = {k: lam[k] * v for k, v in terms.items()}
        total = sum(t.mean() for t in weighted.values())
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
        maps = decode_maps(G.synthesis(inv.ws, noise_mode="const"), G.settings)
    return TuningResult(tuned, maps, history)
