"""A synthetic subject with full ground truth, rendered by our own renderer: for measuring the fit.

``make_subject`` draws an identity (p_s from the shape model's prior), expressions (p_e, one per view),
reflectance maps (BRDF-GAN at a random z, truncated toward the W average), one camera per view (the
first frontal, the others at yaw offsets), random lights per view (ambient + SH environment + one or two
directional lights), renders every view with all effects on a plain or noisy background, then degrades
the renders like a photo (Gaussian blur, sensor noise, JPEG). Everything is drawn from one
``numpy.random.Generator`` seeded by ``SyntheticSettings.seed``: the same settings give the same photos.
A bearded z is redrawn (``SyntheticSettings.max_off_tone``) from streams of its own, so the rest of the
scene stays the seed's.

The subject knows what the fit should recover (``p_s``, ``p_e``, ``ws``, ``maps``, ``cameras``, ``lights``)
and where the landmarks truly are (``landmarks``: the 468 FaceMesh landmark vertices projected into each
photo), so the metrics in ``fitting/metrics.py`` can score a fit against it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..reflectance.gan.networks import Generator, decode_maps
from ..reflectance.maps import ReflectanceMaps
from ..render import Camera, Effects, Lights, Renderer
from ..render.camera import focal_px_from_35mm, frontal_rotation, project
from ..render.shading import srgb_to_linear

__all__ = ["SyntheticSettings", "SyntheticSubject", "make_subject", "off_tone_fraction", "view_yaws"]


@dataclass(frozen=True)
class SyntheticSettings:
    """How a synthetic subject is drawn, posed, lit, rendered and degraded.

    Scales are in units of the shape model's prior standard deviations: ``identity_scale`` = 1 draws
    p_s ~ N(0, diag(lambda)); expression activations are |N(0, (expression_scale sigma_e)^2)| clipped to
    [0, 1] (blendshapes are one-sided). Angles are degrees, distances mm, noise in 8-bit sRGB levels."""

    size: int = 512  # photo side in pixels (square)
    n_views: int = 1  # the first frontal, the others at yaw offsets
    yaw_range_deg: float = 30.0  # extra views spread over [-yaw, +yaw], alternating sides, the widest at +-yaw
    pose_jitter_deg: float = 3.0  # random extra rotation of every view about each axis (std)
    distance_mm: float = 450.0  # camera to the model origin (the landmarks' centroid)
    focal_35mm: float = 50.0  # 35 mm equivalent focal length (what EXIF would say)
    identity_scale: float = 1.0
    expression_scale: float = 0.15
    truncation: float = 0.7  # W = w_avg + truncation (w - w_avg): plausible maps
    # Redraw z while more than this fraction of the face's "skin" texels is off the forehead tone
    # (beards, heavy stubble): the photo skin mask keeps them out of the fit by design, so no fit can
    # recover them and they would measure the mask, not the fit. 1.0: never redraw. 0.15: of 96 draws
    # of the 125 kimg G at psi 0.7, the 81 clean faces (redness, freckles) scored <= 0.15 and the 15
    # bearded or stubbled ones 0.17-0.54, looked at (docs/fitting_synthetic.md).
    max_off_tone: float = 0.15
    max_redraws: int = 20  # then keep the least off-tone draw
    randomise_lights: bool = True  # False: Lights.frontal() in every view
    max_lights: int = 2  # directional lights per view, 1..max_lights drawn at random
    ambient_range: tuple[float, float] = (0.2, 0.45)  # linear ambient level
    key_range: tuple[float, float] = (0.5, 0.9)  # linear key-light intensity
    key_cone_deg: float = 40.0  # the key light comes from within this angle of the camera
    light_tint: float = 0.08  # per-channel relative variation of light colours
    background: str = "plain"  # "plain": a random grey-ish colour; "noise": that plus blurred noise
    blur_sigma: float = 0.7  # Gaussian blur in pixels (0: none)
    noise_sigma: float = 2.0  # additive Gaussian noise, 8-bit levels (0: none)
    jpeg_quality: int | None = 90  # None: no JPEG round trip
    seed: int = 0

    def __post_init__(self) -> None:
        if self.size < 64:
            raise ValueError(f"SyntheticSettings.size must be >= 64, got {self.size}")
        if self.n_views < 1:
            raise ValueError(f"SyntheticSettings.n_views must be >= 1, got {self.n_views}")
        if not 0 <= self.yaw_range_deg <= 80:
            raise ValueError(f"SyntheticSettings.yaw_range_deg must be in [0, 80], got {self.yaw_range_deg}")
        if self.distance_mm <= 150:
            raise ValueError(f"SyntheticSettings.distance_mm must be > 150 (the head's depth), got {self.distance_mm}")
        if self.focal_35mm <= 0:
            raise ValueError(f"SyntheticSettings.focal_35mm must be > 0, got {self.focal_35mm}")
        for name in ("identity_scale", "expression_scale", "pose_jitter_deg", "light_tint", "blur_sigma", "noise_sigma"):
            if getattr(self, name) < 0:
                raise ValueError(f"SyntheticSettings.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.max_off_tone <= 1:
            raise ValueError(f"SyntheticSettings.max_off_tone must be in (0, 1], got {self.max_off_tone}")
        if self.max_redraws < 0:
            raise ValueError(f"SyntheticSettings.max_redraws must be >= 0, got {self.max_redraws}")
        if not 0 <= self.truncation <= 1:
            raise ValueError(f"SyntheticSettings.truncation must be in [0, 1], got {self.truncation}")
        if self.max_lights < 1:
            raise ValueError(f"SyntheticSettings.max_lights must be >= 1, got {self.max_lights}")
        for name in ("ambient_range", "key_range"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"SyntheticSettings.{name} must be (lo, hi) with 0 <= lo <= hi, got {(lo, hi)}")
        if self.background not in ("plain", "noise"):
            raise ValueError(f"SyntheticSettings.background must be 'plain' or 'noise', got {self.background!r}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"SyntheticSettings.jpeg_quality must be None or in [1, 100], got {self.jpeg_quality}")


@dataclass(frozen=True)
class SyntheticSubject:
    """One synthetic person seen in V photos, with the ground truth of everything the fit estimates.

    photos: (V, H, W, 3) uint8 sRGB, the degraded renders (what a fit sees).
    clean: (V, H, W, 3) uint8 sRGB, the renders before blur, noise and JPEG.
    masks: (V, H, W) bool, pixels whose centre the mesh covers.
    p_s: (1, K) float32 identity coefficients; p_e: (V, E) float32 expression activations, one row per view.
    z: (1, z_dim) float32 the latent; ws: (1, num_ws, w_dim) float32 the truncated W the maps come from; both
    None when the maps were given (``make_subject``'s ``maps``).
    z_redraws: how many z were rejected as off-tone before this one (0: the seed's first draw).
    off_tone: fraction of the face's "skin" texels off the forehead tone (``off_tone_fraction``).
    maps: ReflectanceMaps (1, ., R, R): albedo linear [0, 1], specular linear [0, 1], unit tangent-space normals.
    cameras: Camera, batch V, in photo pixels (focal, principal), rotation world -> camera, translation mm.
    lights: Lights, batch V: ambient (V, 3) linear, direction (V, L, 3) unit (world), colour (V, L, 3)
    linear, sh (V, 9, 3); L is the largest light count drawn (views with fewer lights have black extras).
    vertices: (V, N, 3) float32 world mm, the posed mesh of each view (p_s with that view's p_e).
    neutral: (N, 3) float32 world mm, the identity with no expression.
    landmarks: (V, 468, 2) float32 photo pixels, the FaceMesh landmark vertices projected (occluded ones too).
    ibug68: (V, 68, 2) float32 photo pixels, the iBUG-68 subset (``shape_model.ibug68``).
    yaws_deg: (V,) float64 the nominal yaw of each view (before jitter).
    effects: the effects the photos were rendered with.
    """

    photos: np.ndarray
    clean: np.ndarray
    masks: np.ndarray
    p_s: torch.Tensor
    p_e: torch.Tensor
    z: torch.Tensor | None
    ws: torch.Tensor | None
    maps: ReflectanceMaps
    cameras: Camera
    lights: Lights
    vertices: torch.Tensor
    neutral: torch.Tensor
    landmarks: np.ndarray
    ibug68: np.ndarray
    yaws_deg: np.ndarray
    effects: Effects
    settings: SyntheticSettings
    z_redraws: int
    off_tone: float

    @property
    def n_views(self) -> int:
        return int(self.photos.shape[0])


def view_yaws(n_views: int, yaw_range_deg: float) -> np.ndarray:
    """(n_views,) nominal yaws in degrees: 0 first, then alternating +/- with growing magnitude so that
    the widest pair is at +-yaw_range_deg (e.g. 3 views at 30: 0, +30, -30; 5 views: 0, +15, -15, +30, -30)."""
    if n_views < 1:
        raise ValueError(f"n_views must be >= 1, got {n_views}")
    extra = n_views - 1
    steps = max(1, math.ceil(extra / 2))
    yaws = [0.0]
    for k in range(extra):
        mag = yaw_range_deg * (k // 2 + 1) / steps
        yaws.append(mag if k % 2 == 0 else -mag)
    return np.array(yaws, np.float64)


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World-frame head rotation (degrees): yaw about +y, pitch about +x, roll about +z."""
    y, p, r = np.radians([yaw, pitch, roll])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return rz @ rx @ ry


def _cameras(s: SyntheticSettings, yaws: np.ndarray, rng: np.random.Generator) -> Camera:
    """One camera per view looking at the model origin from ``distance_mm``; the head turned by the
    view's yaw (plus jitter). Yaw > 0 turns the face toward the subject's left (the image's right)."""
    v = len(yaws)
    f = focal_px_from_35mm(s.focal_35mm, s.size, s.size)
    base = frontal_rotation(1, dtype=torch.float64)[0].numpy()
    rots = []
    for yaw in yaws:
        jit = rng.normal(0.0, s.pose_jitter_deg, 3) if s.pose_jitter_deg > 0 else np.zeros(3)
        rots.append(base @ _rotation(yaw + jit[0], jit[1], jit[2]))
    t = torch.tensor
    return Camera(t([[f, f]] * v, dtype=torch.float32), t([[s.size / 2, s.size / 2]] * v, dtype=torch.float32),
                  t(np.stack(rots), dtype=torch.float32), t([[0.0, 0.0, s.distance_mm]] * v, dtype=torch.float32),
                  s.size, s.size)


def _random_direction(axis: np.ndarray, cone_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A unit vector within ``cone_deg`` of ``axis`` (uniform over the cap's area)."""
    axis = axis / np.linalg.norm(axis)
    cos_max = math.cos(math.radians(cone_deg))
    c = rng.uniform(cos_max, 1.0)
    phi = rng.uniform(0, 2 * math.pi)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    sn = math.sqrt(max(0.0, 1 - c * c))
    return c * axis + sn * (math.cos(phi) * u + math.sin(phi) * w)


def _lights(s: SyntheticSettings, cams: Camera, rng: np.random.Generator) -> Lights:
    """Per view: ambient, an SH environment (the ambient, a little brighter from above, slightly
    tinted), a key light near the camera and possibly a fill light from the side."""
    v = cams.batch
    if not s.randomise_lights:
        return Lights.frontal(v)
    # the camera centre in the world: -R^T t
    eyes = -np.einsum("vji,vj->vi", cams.rotation.double().numpy(), cams.translation.double().numpy())
    n_lights = rng.integers(1, s.max_lights + 1, size=v)
    nl = int(n_lights.max())
    amb, dirs, cols, sh = np.zeros((v, 3)), np.zeros((v, nl, 3)), np.zeros((v, nl, 3)), np.zeros((v, 9, 3))
    for i in range(v):
        tint = lambda: 1 + rng.uniform(-s.light_tint, s.light_tint, 3)  # noqa: E731
        a = rng.uniform(*s.ambient_range) * tint()
        amb[i] = a
        sh[i, 0] = a * 2 * math.sqrt(math.pi)  # the constant term: irradiance = a
        sh[i, 2] = a * rng.uniform(0.0, 0.4) * 2 * math.sqrt(math.pi / 3)  # brighter from above (+y)
        sh[i, 3] = a * rng.uniform(-0.2, 0.2) * 2 * math.sqrt(math.pi / 3)  # a little from one side (x)
        # the key light: near the camera, biased upward like most photos
        view_dir = eyes[i] / np.linalg.norm(eyes[i])
        dirs[i, 0] = _random_direction(view_dir + np.array([0, 0.25, 0]), s.key_cone_deg, rng)
        cols[i, 0] = rng.uniform(*s.key_range) * tint()
        for j in range(1, int(n_lights[i])):  # fill lights: from a side, weaker
            side = np.array([rng.choice([-1.0, 1.0]), 0.0, 0.0])
            dirs[i, j] = _random_direction(view_dir + 1.2 * side, 25.0, rng)
            cols[i, j] = rng.uniform(0.15, 0.4) * rng.uniform(*s.key_range) * tint()
        for j in range(int(n_lights[i]), nl):  # padding: a black light (contributes nothing)
            dirs[i, j] = dirs[i, 0]
    t = lambda x: torch.tensor(x, dtype=torch.float32)  # noqa: E731
    return Lights(t(amb), t(dirs), t(cols), sh=t(sh))


def _background(s: SyntheticSettings, v: int, rng: np.random.Generator) -> torch.Tensor:
    """(V, 3, H, W) linear background: a random muted colour per view (plus blurred noise)."""
    out = np.empty((v, 3, s.size, s.size), np.float32)
    for i in range(v):
        grey = rng.uniform(0.15, 0.6)
        colour = np.clip(grey * (1 + rng.uniform(-0.15, 0.15, 3)), 0, 1)  # sRGB
        img = np.broadcast_to(colour[:, None, None], (3, s.size, s.size)).astype(np.float32)
        if s.background == "noise":
            noise = rng.normal(0, 1, (s.size // 8, s.size // 8, 3)).astype(np.float32)
            noise = cv2.resize(noise, (s.size, s.size), interpolation=cv2.INTER_CUBIC)
            img = np.clip(img + 0.08 * noise.transpose(2, 0, 1), 0, 1)
        out[i] = img
    return srgb_to_linear(torch.from_numpy(out))


def off_tone_fraction(albedo: torch.Tensor, region_uv: torch.Tensor) -> float:
    """Fraction of the face's "skin" region (cheeks, chin, upper lip, jaw: not forehead, brows, eyes, nose,
    lips) whose albedo is off the forehead's skin tone: augmentation's mask M (``reflectance.augment``)
    below 0.5. ``albedo``: (1, 3, R, R) linear [0, 1], UV layout; ``region_uv``: the shape model's (S, S)
    label map. Measured on 96 draws of the 125 kimg G: beards and heavy stubble 0.17-0.54, clean skin
    (redness and freckles included) 0-0.15."""
    if albedo.ndim != 4 or albedo.shape[:2] != (1, 3) or albedo.shape[2] != albedo.shape[3]:
        raise ValueError(f"albedo must be (1, 3, R, R), got {tuple(albedo.shape)}")
    from ..reflectance.augment import skin_mask
    from ..shape.regions import region_masks

    a = albedo[0].permute(1, 2, 0).float().cpu().numpy()
    m = region_masks(region_uv.cpu().numpy().astype(np.uint8), a.shape[0])
    return float((skin_mask(a, m["forehead"], m["mapped"])[m["skin"]] < 0.5).mean())


def _degrade(img: np.ndarray, s: SyntheticSettings, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) uint8 sRGB -> blurred, noisy, JPEG-compressed (H, W, 3) uint8 sRGB."""
    x = img.astype(np.float32)
    if s.blur_sigma > 0:
        x = cv2.GaussianBlur(x, (0, 0), s.blur_sigma, borderType=cv2.BORDER_REFLECT)
    if s.noise_sigma > 0:
        x = x + rng.normal(0.0, s.noise_sigma, x.shape).astype(np.float32)
    out = np.clip(np.round(x), 0, 255).astype(np.uint8)
    if s.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(s.jpeg_quality)])
        if not ok:
            raise RuntimeError("cv2.imencode failed to write a JPEG")
        out = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return out


def make_subject(G: Generator, shape_model, renderer: Renderer | None = None,
                 settings: SyntheticSettings = SyntheticSettings(), maps: ReflectanceMaps | None = None) -> SyntheticSubject:
    """Draw and render one synthetic subject (see the module docstring). ``G``: the BRDF-GAN;
    ``shape_model``: a ``ShapeModel``; ``renderer``: ``Renderer.for_shape_model(shape_model)`` (built
    when None). Runs on the CPU, under ``torch.no_grad``; deterministic for given settings.

    ``maps``: reflectance maps (1, ., R, R) at G's resolution to use instead of G's, e.g. a held-out sample of the
    training data, so that the subject does not depend on the generator a fit uses (``bench.dataset``). The
    subject's z and ws are then None and nothing is redrawn; identity, cameras and lights are the seed's, as for
    the G-drawn subject of the same seed."""
    s = settings
    if not isinstance(s, SyntheticSettings):
        raise ValueError(f"settings must be a SyntheticSettings, got {type(s).__name__}")
    for name in ("mean", "identity_eigenvalues", "expression_scale", "landmarks", "ibug68", "region_uv"):
        if not hasattr(shape_model, name):
            raise ValueError(f"shape_model has no {name!r}: expected a fitme ShapeModel")
    if not hasattr(G, "mapping") or not hasattr(G, "synthesis"):
        raise ValueError(f"G must be a BRDF-GAN Generator, got {type(G).__name__}")
    gs = G.settings
    if maps is not None:
        want = {"albedo": 3, "specular": 1, "normals": 3}
        got = {k: tuple(getattr(maps, k).shape) for k in want}
        if any(g != (1, c, gs.resolution, gs.resolution) for g, c in zip(got.values(), want.values())):
            raise ValueError(f"maps must be (1, C, {gs.resolution}, {gs.resolution}) albedo 3, specular 1, normals 3 "
                             f"channels, got {got}")
    if renderer is None:
        renderer = Renderer.for_shape_model(shape_model)
    if renderer.n_vertices != shape_model.mean.shape[0]:
        raise ValueError(f"renderer is for {renderer.n_vertices} vertices, the shape model has {shape_model.mean.shape[0]}")

    rng = np.random.default_rng(s.seed)
    v = s.n_views
    kw = {"dtype": shape_model.mean.dtype, "device": shape_model.mean.device}
    with torch.no_grad():
        # identity and expressions
        p_s = torch.tensor(rng.normal(0.0, 1.0, (1, shape_model.n_identity)), **kw)
        p_s = p_s * s.identity_scale * shape_model.identity_eigenvalues.sqrt()
        sig_e = shape_model.expression_scale.double().cpu().numpy()
        act = np.abs(rng.normal(0.0, 1.0, (v, shape_model.n_expressions))) * s.expression_scale * sig_e
        p_e = torch.tensor(np.clip(act, 0.0, 1.0), **kw)
        # reflectance: the seed's own z first; redraws come from their own streams, so a subject that
        # needs none is the same as before redraws existed, and the rest of the scene never changes
        best = None
        if maps is not None:
            rng.normal(0.0, 1.0, (1, gs.z_dim))  # the seed's z, drawn and unused: the scene stays the seed's
            maps = ReflectanceMaps(*(t.detach().float().to(G.w_avg.device) for t in (maps.albedo, maps.specular, maps.normals)))
            best = (off_tone_fraction(maps.albedo, shape_model.region_uv), 0, None, None, maps)
        for k in range(s.max_redraws + 1 if maps is None else 0):
            zr = rng if k == 0 else np.random.default_rng([s.seed, k])
            z = torch.tensor(zr.normal(0.0, 1.0, (1, gs.z_dim)), dtype=torch.float32, device=G.w_avg.device)
            ws = G.ws(z, truncation_psi=s.truncation)
            maps = decode_maps(G.synthesis(ws, noise_mode="const"), gs)
            off = off_tone_fraction(maps.albedo, shape_model.region_uv)
            if best is None or off < best[0]:
                best = (off, k, z, ws, maps)
            if off <= s.max_off_tone:
                break
        off, redraws, z, ws, maps = best
        # geometry, cameras, lights
        yaws = view_yaws(v, s.yaw_range_deg)
        cams = _cameras(s, yaws, rng)
        lights = _lights(s, cams, rng)
        bg = _background(s, v, rng)
        shp = shape_model(p_s.expand(v, -1), p_e)
        neutral = shape_model.vertices(p_s, torch.zeros_like(p_e[:1]))[0]
        effects = Effects.all()
        dev = shp.vertices.device
        out = renderer(shp.vertices, shp.normals, shp.tangents, maps, _to(cams, dev), _to(lights, dev), effects,
                       background=bg.to(dev))
        clean = (out.image.clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy() * 255).round().astype(np.uint8)
        px = project(shp.vertices[:, shape_model.landmarks], _to(cams, dev))[..., :2].cpu().numpy().astype(np.float32)
        i68 = px[:, shape_model.ibug68.cpu().numpy()]
    photos = np.stack([_degrade(c, s, rng) for c in clean])
    return SyntheticSubject(photos, clean, out.mask[:, 0].cpu().numpy() > 0.5, p_s.float().cpu(), p_e.float().cpu(),
                            None if z is None else z.cpu(), None if ws is None else ws.cpu(),
                            ReflectanceMaps(*(t.cpu() for t in (maps.albedo, maps.specular, maps.normals))),
                            cams, lights, shp.vertices.float().cpu(), neutral.float().cpu(), px, i68, yaws, effects, s,
                            redraws, off)


def _to(x, device):
    """A Camera or Lights on ``device`` (the synthetic scene is built on the CPU)."""
    if isinstance(x, Camera):
        return Camera(x.focal.to(device), x.principal.to(device), x.rotation.to(device), x.translation.to(device),
                      x.width, x.height, x.near)
    return Lights(x.ambient.to(device), x.direction.to(device), x.colour.to(device),
                  None if x.position is None else x.position.to(device), None if x.sh is None else x.sh.to(device))
