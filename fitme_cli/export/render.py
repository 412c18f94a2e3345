"""Relighting for ``fitme render``: preset light environments, a turntable, and a contact sheet.

The avatar (the closed head of ``mesh.py`` with the filled maps of ``maps.py`` at the avatar's own
resolution) is rendered by our differentiable renderer (``fitme_cli.render``) with every effect a
scene calls for. Rows of the sheet are environments, columns are turntable yaws: the head turns about
the vertical axis through its centre while camera and lights stay fixed, as on a real turntable.

Directions: world frame (x to the subject's left, y up, z out of the face toward the camera). A light
at azimuth ``az`` and elevation ``el`` (degrees) shines from (sin az cos el, sin el, cos az cos el):
az = 0 from the camera, az = 90 from the subject's left (the viewer's right), el = 90 from above.
Colours are linear RGB in the renderer's units (1 = a light that makes albedo-1 skin facing it white).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["Light", "Environment", "ENVIRONMENTS", "PHOTO_ENVIRONMENT", "DEFAULT_ENVIRONMENTS", "SheetSettings",
           "parse_environments", "parse_light", "parse_expression", "turntable_yaws", "render_sheet"]


def _direction(az_deg: float, el_deg: float) -> tuple[float, float, float]:
    a, e = math.radians(az_deg), math.radians(el_deg)
    return (math.sin(a) * math.cos(e), math.sin(e), math.cos(a) * math.cos(e))


@dataclass(frozen=True)
class Light:
    """A directional light: ``direction`` unit vector toward the light (world); ``colour`` linear RGB."""

    direction: tuple[float, float, float]
    colour: tuple[float, float, float]

    @staticmethod
    def at(az_deg: float, el_deg: float, colour: tuple[float, float, float]) -> Light:
        return Light(_direction(az_deg, el_deg), colour)


@dataclass(frozen=True)
class Environment:
    """ambient: linear RGB; lights: key first; sky, ground: when set, an SH hemisphere environment
    (irradiance ``sky`` from straight above, ``ground`` from below) replaces the constant ambient;
    shadows: self-shadowing from the lights."""

    name: str
    description: str
    ambient: tuple[float, float, float]
    lights: tuple[Light, ...]
    sky: tuple[float, float, float] | None = None
    ground: tuple[float, float, float] | None = None
    shadows: bool = True


ENVIRONMENTS: dict[str, Environment] = {e.name: e for e in (
    Environment("studio", "three-point: warm key upper left, soft fill right, rim from behind", (0.10, 0.10, 0.10),
                (Light.at(-35, 30, (1.25, 1.18, 1.08)), Light.at(50, 5, (0.35, 0.38, 0.42)), Light.at(160, 40, (0.7, 0.7, 0.75)))),
    Environment("outdoor", "overcast sky above, grey-green ground bounce, soft sun high on the right", (0.0, 0.0, 0.0),
                (Light.at(40, 60, (0.95, 0.9, 0.8)),), sky=(0.45, 0.52, 0.62), ground=(0.12, 0.13, 0.10)),
    Environment("sunset", "low orange sun from the left, blue sky fill from the right", (0.0, 0.0, 0.0),
                (Light.at(-70, 8, (1.5, 0.68, 0.3)), Light.at(60, 30, (0.12, 0.17, 0.32))),
                sky=(0.14, 0.16, 0.26), ground=(0.06, 0.04, 0.03)),
    Environment("dramatic", "one hard light from the side, almost no ambient", (0.02, 0.02, 0.025),
                (Light.at(85, 15, (1.5, 1.5, 1.5)),)),
    Environment("night", "cool moonlight from above and behind, a dim warm lamp in front", (0.02, 0.025, 0.04),
                (Light.at(150, 55, (0.35, 0.45, 0.75)), Light.at(-20, -10, (0.35, 0.22, 0.1)))),
)}
PHOTO_ENVIRONMENT = "photo"  # the lights fitted to the first photo
DEFAULT_ENVIRONMENTS = ("studio", "outdoor", "sunset", "dramatic")


def parse_environments(spec: str) -> tuple[str, ...]:
    """'studio,sunset' -> names; 'all' -> every preset and the photo's lights. ValueError names the choices."""
    allowed = (*ENVIRONMENTS, PHOTO_ENVIRONMENT)
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if names == ["all"]:
        return allowed
    bad = [n for n in names if n not in allowed]
    if bad or not names:
        raise ValueError(f"unknown environment {', '.join(bad) or repr(spec)}; expected one or more of {', '.join(allowed)} (or all)")
    return tuple(dict.fromkeys(names))


def parse_light(spec: str) -> Light:
    """'AZ,EL[,INTENSITY]' in degrees (see the module docstring), white light -> Light. ValueError on bad input."""
    parts = [p.strip() for p in spec.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"light {spec!r}: expected AZ,EL[,INTENSITY] as numbers, e.g. 30,20,1.2") from None
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise ValueError(f"light {spec!r}: expected 2 or 3 finite numbers AZ,EL[,INTENSITY], got {len(values)}")
    az, el, i = values[0], values[1], values[2] if len(values) == 3 else 1.0
    if not -90.0 <= el <= 90.0:
        raise ValueError(f"light {spec!r}: elevation must be in [-90, 90] degrees, got {el:g}")
    if not 0.0 <= i <= 20.0:
        raise ValueError(f"light {spec!r}: intensity must be in [0, 20], got {i:g}")
    return Light.at(az, el, (i, i, i))


def parse_expression(spec: str, names: list[str], fitted: np.ndarray | None = None) -> np.ndarray:
    """'neutral' | 'fitted' | 'jawOpen=0.5,mouthSmileLeft=0.3' -> (E,) weights. ARKit weights are in
    [0, 1]; names not given are 0. ValueError names the problem (an unknown name lists the close ones)."""
    spec = spec.strip()
    w = np.zeros(len(names), np.float64)
    if spec in ("", "neutral"):
        return w
    if spec == "fitted":
        if fitted is None:
            raise ValueError("expression 'fitted': this avatar has no fitted expression")
        return np.asarray(fitted, np.float64).copy()
    index = {n: i for i, n in enumerate(names)}
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        if "=" not in item:
            raise ValueError(f"expression {item!r}: expected NAME=VALUE (e.g. jawOpen=0.5), 'neutral' or 'fitted'")
        name, value = (s.strip() for s in item.split("=", 1))
        if name not in index:
            import difflib

            close = difflib.get_close_matches(name, names, n=3, cutoff=0.5)
            hint = f"; did you mean {', '.join(close)}?" if close else f"; expected one of the 52 ARKit names ({names[0]}, {names[1]}, ...)"
            raise ValueError(f"unknown expression {name!r}{hint}")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"expression {name}={value!r}: the value must be a number in [0, 1]") from None
        if not (0.0 <= v <= 1.0):
            raise ValueError(f"expression {name}={value}: the value must be in [0, 1], got {v:g}")
        w[index[name]] = v
    return w


def turntable_yaws(n: int) -> list[float]:
    """n yaws in degrees around the full circle, starting frontal: 0, 360/n, ..."""
    if not isinstance(n, int) or not 1 <= n <= 36:
        raise ValueError(f"turntable: expected 1 to 36 views, got {n!r}")
    return [360.0 * k / n for k in range(n)]


@dataclass(frozen=True)
class SheetSettings:
    """environments: names (ENVIRONMENTS or PHOTO_ENVIRONMENT); custom_lights: an extra "custom" row lit
    by these (ambient 0.12); turntable: views per row; size: cell side in pixels; weights: (E,)
    expression; background: linear grey behind the head; labels: draw names and yaws."""

    environments: tuple[str, ...] = DEFAULT_ENVIRONMENTS
    custom_lights: tuple[Light, ...] = ()
    turntable: int = 6
    size: int = 256
    weights: tuple[float, ...] = ()
    background: float = 0.02
    labels: bool = True
    focal_35mm: float = 50.0  # a portrait lens: little perspective distortion
    fill: float = 0.82  # share of the cell height the head's full turn occupies

    def __post_init__(self) -> None:
        if not self.environments and not self.custom_lights:
            raise ValueError("no environment to render")
        allowed = (*ENVIRONMENTS, PHOTO_ENVIRONMENT)
        bad = [e for e in self.environments if e not in allowed]
        if bad:
            raise ValueError(f"unknown environment {', '.join(bad)}; expected {', '.join(allowed)}")
        turntable_yaws(self.turntable)
        if not isinstance(self.size, int) or not 64 <= self.size <= 2048:
            raise ValueError(f"size must be 64..2048 pixels, got {self.size!r}")
        if not 0.0 <= self.background <= 1.0:
            raise ValueError(f"background must be in [0, 1], got {self.background!r}")


def _sh_hemisphere(sky, ground) -> torch.Tensor:
    """(9, 3) irradiance coefficients on ``render.lights.sh_basis`` of E(n) = (sky + ground)/2 +
    (sky - ground)/2 * n_y: the classic hemisphere light."""
    sky, ground = torch.tensor(sky, dtype=torch.float64), torch.tensor(ground, dtype=torch.float64)
    sh = torch.zeros(9, 3, dtype=torch.float64)
    sh[0] = (sky + ground) / 2 * 2 * math.sqrt(math.pi)  # Y_00 = 1 / (2 sqrt(pi))
    sh[1] = (sky - ground) / 2 * 2 * math.sqrt(math.pi / 3)  # Y_1-1 = sqrt(3 / (4 pi)) y
    return sh


def _scene(env: str | None, custom: tuple[Light, ...], source, batch: int):
    """(Lights with batch ``batch``, Effects) for an environment name, or the custom lights when None."""
    from ..render import Effects, Lights

    def rep(t: torch.Tensor) -> torch.Tensor:
        return t.double()[None].expand(batch, *t.shape).clone()

    if env == PHOTO_ENVIRONMENT:
        li = source.lights
        sh = None if li.sh is None else rep(li.sh[0])
        lights = Lights(rep(li.ambient[0]), rep(li.direction[0]), rep(li.colour[0]), sh=sh)
        fx = source.effects
        return lights, Effects(specular=True, subsurface=True, sh_ambient=bool(fx.sh_ambient and sh is not None),
                               shadows=bool(fx.shadows), multi_light=lights.count > 1)
    e = ENVIRONMENTS[env] if env is not None else Environment("custom", "--light", (0.12, 0.12, 0.12), custom, shadows=True)
    d = torch.nn.functional.normalize(torch.tensor([lt.direction for lt in e.lights], dtype=torch.float64), dim=-1)
    c = torch.tensor([lt.colour for lt in e.lights], dtype=torch.float64)
    sh = _sh_hemisphere(e.sky, e.ground) if e.sky is not None else None
    lights = Lights(rep(torch.tensor(e.ambient, dtype=torch.float64)), rep(d), rep(c), sh=None if sh is None else rep(sh))
    return lights, Effects(specular=True, subsurface=True, sh_ambient=sh is not None, shadows=e.shadows,
                           multi_light=len(e.lights) > 1)


def _wrapped_texture(maps, u_max: float):
    """Maps widened by columns wrapped from u = 0, so triangles across the back seam (u up to ``u_max``)
    read the texels a wrapping sampler would (the renderer clamps at the border). Returns (maps, scale
    for u)."""
    from ..reflectance.maps import ReflectanceMaps

    r = maps.albedo.shape[0]
    extra = max(0, int(math.ceil((u_max - 1.0) * r)) + 2)

    def t(x: np.ndarray) -> torch.Tensor:
        x = x if x.ndim == 3 else x[..., None]
        x = np.concatenate([x, x[:, :extra]], 1)
        return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].double()

    return ReflectanceMaps(t(maps.albedo), t(maps.specular), t(maps.normals)), r / (r + extra)


def _yaw_matrix(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]], dtype=torch.float64)


def render_sheet(source, shape_model, settings: SheetSettings = SheetSettings()) -> tuple[np.ndarray, list[str], list[float]]:
    """The contact sheet: (rows * size, columns * size, 3) uint8 sRGB, the row names and the column yaws.
    ``source``: an ``AvatarSource``."""
    import cv2

    from ..render import Camera, Renderer
    from ..render.camera import focal_px_from_35mm, frontal_rotation
    from .maps import MapSettings, prepare_maps
    from .mesh import geometry, head_topology, head_vertices

    topo = head_topology(shape_model)
    E = shape_model.n_expressions
    w = np.asarray(settings.weights, np.float64) if len(settings.weights) else np.zeros(E)
    if w.shape != (E,):
        raise ValueError(f"weights: expected {E} expression weights, got {w.shape}")
    r = int(source.maps.albedo.shape[0])
    maps = prepare_maps(source.maps, topo.uv, topo.uv_faces, MapSettings(r))
    tex, u_scale = _wrapped_texture(maps, float(topo.uv[:, 0].max()))
    uv = torch.from_numpy(topo.uv * [u_scale, 1.0])
    renderer = Renderer(torch.from_numpy(topo.triangles), uv, torch.from_numpy(topo.uv_faces), topo.n_vertices).double()

    p_s = torch.from_numpy(np.asarray(source.p_s, np.float64))[None]
    verts = head_vertices(shape_model, topo, p_s, torch.from_numpy(w)[None])[0]  # (P, 3) mm
    lo, hi = verts.min(0).values, verts.max(0).values
    centre = (lo + hi) / 2
    centre[0] = 0.0  # the model is symmetric about x = 0: turn about the head's own axis
    half_h = float((hi[1] - lo[1]) / 2)
    radius = float(((verts[:, [0, 2]] - centre[[0, 2]]) ** 2).sum(1).sqrt().max())

    yaws = turntable_yaws(settings.turntable)
    b, s = len(yaws), settings.size
    f = focal_px_from_35mm(settings.focal_35mm, s, s)
    dist = f * half_h / (settings.fill * s / 2) + radius  # the head's height fills `fill`, nearest point included
    rot = frontal_rotation(b, dtype=torch.float64)
    t = torch.tensor([-float(centre[0]), float(centre[1]), dist + float(centre[2])], dtype=torch.float64).expand(b, 3).clone()
    cam = Camera(torch.full((b, 2), f, dtype=torch.float64), torch.full((b, 2), s / 2, dtype=torch.float64), rot, t, s, s)
    turned = torch.stack([(verts - centre) @ _yaw_matrix(y).T + centre for y in yaws])  # (B, P, 3)
    v, n, tg = geometry(topo, turned)
    bg = torch.full((b, 3, s, s), settings.background, dtype=torch.float64)

    rows, names = [], []
    scenes = [(e, e) for e in settings.environments] + ([("custom", None)] if settings.custom_lights else [])
    for label, env in scenes:
        lights, effects = _scene(env, settings.custom_lights, source, b)
        with torch.no_grad():
            out = renderer(v, n, tg, tex, cam, lights, effects, background=bg)
        img = (out.image.clamp(0, 1).permute(0, 2, 3, 1).numpy() * 255 + 0.5).astype(np.uint8)
        row = np.concatenate(list(img), 1)
        if settings.labels:
            row = np.ascontiguousarray(row)
            scale = max(0.35, s / 512)
            cv2.putText(row, label, (6, int(18 * scale / 0.5)), cv2.FONT_HERSHEY_SIMPLEX, scale, (235, 235, 235), 1, cv2.LINE_AA)
            for k, y in enumerate(yaws):
                cv2.putText(row, f"{y:.0f} deg", (k * s + 6, s - 8), cv2.FONT_HERSHEY_SIMPLEX, scale * 0.85, (170, 170, 170),
                            1, cv2.LINE_AA)
        rows.append(row)
        names.append(label)
    return np.concatenate(rows, 0), names, yaws
