"""Numerical stability of the renderer on the hard cases: grazing light and view, a light opposite the
view (zero half vector), shininess up to 1e4, zero-length normals, degenerate / sliver triangles,
geometry crossing the near plane or behind the camera, a face filling the image and one 10 px wide,
black and saturated textures, float32 vs float64.

Each case reports three checks: the forward pass is finite; the backward pass (d image.sum() w.r.t.
vertices, normals, maps and lights) is finite; and, where the function is smooth at that point, autograd
agrees with float64 finite differences (``torch.autograd.gradcheck``, at the shading-function level or on
a tiny render); None where no such check applies. ``benchmarks/render_stability.py`` prints the matrix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import pytest
import torch

from fitme_cli.reflectance.maps import ReflectanceMaps
from fitme_cli.render.camera import Camera, frontal_rotation, project
from fitme_cli.render.effects import Effects
from fitme_cli.render.lights import Lights
from fitme_cli.render.raster import barycentrics, rasterize
from fitme_cli.render.renderer import Renderer, RenderSettings
from fitme_cli.render.shading import (diffuse_irradiance, linear_to_srgb, safe_normalize, specular_reflectance,
                                      tangent_to_world)
from render_scenes import bump_mesh  # tests/ is on sys.path (pytest rootdir conftest)

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")


# ----------------------------------------------------------------------------------------------- scenes


def procedural_maps(r=8, albedo=None, specular=None, tilt=0.25, dtype=F64):
    u = (torch.arange(r, dtype=dtype) + 0.5) / r
    vv, uu = torch.meshgrid(u, u, indexing="ij")
    a = torch.stack([0.5 + 0.1 * torch.sin(6 * uu), 0.35 + 0.05 * torch.cos(5 * vv), 0.28 + 0 * uu])[None]
    if albedo is not None:
        a = torch.full_like(a, albedo)
    s = torch.full((1, 1, r, r), 0.3 if specular is None else specular, dtype=dtype)
    n = torch.stack([tilt * torch.sin(2 * math.pi * uu), tilt * torch.sin(2 * math.pi * vv), torch.ones_like(uu)])
    return ReflectanceMaps(a, s, safe_normalize(n.permute(1, 2, 0)).permute(2, 0, 1)[None].contiguous())


def scene_lights(direction=((0.4, 0.5, 1.0), (-0.7, 0.1, 0.5)), position=None, intensity=0.8, dtype=F64):
    d = torch.tensor([direction], dtype=dtype)
    sh = torch.zeros(1, 9, 3, dtype=dtype)
    sh[:, 0] = 0.3 * 2 * math.sqrt(math.pi)
    sh[:, 2] = 0.1
    return Lights(torch.full((1, 3), 0.3, dtype=dtype), d, torch.full(d.shape, intensity, dtype=dtype),
                  None if position is None else torch.tensor([position], dtype=dtype), sh)


def frontal_camera(distance=100.0, size=24, f=30.0, rotation=None, dtype=F64):
    """Slightly off-centre, so that no pixel centre lies exactly on an edge of the symmetric bump (see
    test_render_ops.test_shared_edge_through_pixel_centre_is_watertight)."""
    r = frontal_rotation(1, dtype=dtype) if rotation is None else rotation
    return Camera(torch.tensor([[f, f]], dtype=dtype), torch.tensor([[size / 2 + 0.137, size / 2 - 0.071]], dtype=dtype), r,
                  torch.tensor([[0.0, 0.0, distance]], dtype=dtype), size, size)


@dataclass
class Scene:
    verts: torch.Tensor
    normals: torch.Tensor
    tangents: torch.Tensor
    faces: torch.Tensor
    uv: torch.Tensor
    maps: ReflectanceMaps
    camera: Camera
    lights: Lights
    settings: RenderSettings = RenderSettings()
    effects: Effects = Effects.all()
    shininess_map: torch.Tensor | None = None


def bump_scene(dtype=F64, **kw) -> Scene:
    verts, normals, tangents, faces, uv, _ = bump_mesh(dtype=dtype)
    s = Scene(verts, normals, tangents, faces, uv, procedural_maps(dtype=dtype), frontal_camera(dtype=dtype),
              scene_lights(dtype=dtype))
    return replace(s, **kw)


def render_grads(s: Scene, image: str = "image") -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Render, backward image.sum(); returns the image and the gradients of every input."""
    leaves = {"vertices": s.verts, "normals": s.normals, "tangents": s.tangents, "albedo": s.maps.albedo,
              "specular": s.maps.specular, "normal map": s.maps.normals, "light direction": s.lights.direction,
              "light colour": s.lights.colour, "ambient": s.lights.ambient, "sh": s.lights.sh}
    if s.lights.position is not None:
        leaves["light position"] = s.lights.position
    if s.shininess_map is not None:
        leaves["shininess map"] = s.shininess_map
    x = {k: v.detach().clone().requires_grad_() for k, v in leaves.items()}
    lights = Lights(x["ambient"], x["light direction"], x["light colour"], x.get("light position"), x["sh"])
    r = Renderer(s.faces, s.uv, s.faces, s.verts.shape[1], s.settings)
    out = r(x["vertices"], x["normals"], x["tangents"], ReflectanceMaps(x["albedo"], x["specular"], x["normal map"]),
            s.camera, lights, s.effects, shininess_map=x.get("shininess map"))
    img = getattr(out, image)
    img.sum().backward()
    return img.detach(), {k: v.grad for k, v in x.items()}


def finite_render(s: Scene) -> tuple[bool, bool]:
    img, grads = render_grads(s)
    bad = [k for k, g in grads.items() if g is not None and not torch.isfinite(g).all()]
    return bool(torch.isfinite(img).all()), not bad


def _gc(fn, *inputs, **kw) -> bool:
    """float64 gradcheck; False (not an exception) on disagreement."""
    x = [t.detach().to(F64).clone().requires_grad_() for t in inputs]
    return bool(torch.autograd.gradcheck(fn, x, raise_exception=False, **kw))


def _lights1(d, colour=(0.9, 0.8, 0.7), position=None):
    d = torch.as_tensor(d, dtype=F64).reshape(1, -1, 3)
    c = torch.tensor(colour, dtype=F64).expand(1, d.shape[1], 3).clone()
    return Lights(torch.full((1, 3), 0.2, dtype=F64), d, c, position)


def _spec_fn(shininess, lights_fn):
    def f(ns, nd, p, eye, d):
        return specular_reflectance(ns, nd, p, eye, lights_fn(d), shininess)
    return f


# ----------------------------------------------------------------------------------------------- cases
# Each case: (dtype) -> (forward finite, backward finite, gradcheck True/False/None)


def case_grazing_light(exact: bool):
    """The light in the plane of the flat part of the mesh: N . L = 0 (exactly, or 1e-9 above)."""
    eps = 0.0 if exact else 1e-9
    fw, bw = finite_render(bump_scene(lights=scene_lights(direction=((1.0, 0.0, eps), (0.0, -1.0, eps)))))
    # shading level, on the smooth side of the max(0, .) and facing kinks (N . L = 1e-3)
    n = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]]], dtype=F64)
    p = torch.tensor([[[0.0, 0.0, 0.0], [5.0, 1.0, 2.0]]], dtype=F64)
    d = torch.tensor([[[1.0, 0.0, 1e-3]]], dtype=F64)
    gc = _gc(lambda nn, dd: diffuse_irradiance(nn, p, _lights1(dd)), n, d)
    gc &= _gc(_spec_fn(30.0, _lights1), n, n, p, torch.tensor([[3.0, 2.0, 100.0]], dtype=F64), d)
    return fw, bw, gc


def case_grazing_view(exact: bool):
    """The camera in the plane of the mesh (seen edge-on): N . V = 0."""
    ang = math.pi / 2 if exact else math.pi / 2 - 1e-4
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(ang), -math.sin(ang)], [0.0, math.sin(ang), math.cos(ang)]], dtype=F64)
    cam = frontal_camera(rotation=(frontal_rotation(1, dtype=F64)[0] @ rx)[None], distance=150.0)
    fw, bw = finite_render(bump_scene(camera=cam))
    n = torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64)
    p = torch.zeros(1, 1, 3, dtype=F64)
    eye = torch.tensor([[0.0, 100.0, 1e-12 if exact else 1e-2]], dtype=F64)
    gc = _gc(_spec_fn(30.0, _lights1), n, n, p, eye, torch.tensor([[[0.0, 0.3, 1.0]]], dtype=F64))
    return fw, bw, gc


def case_nh_zero_high_shininess(shininess: float):
    """Detail normals at right angles to the half vector (N . H ~ 0) with a high exponent: the lobe
    underflows to 0, its gradient must stay finite (no 0 * inf)."""
    maps = procedural_maps()
    ts = safe_normalize(torch.tensor([1.0, 0.0, 1e-4], dtype=F64)).view(1, 3, 1, 1).expand_as(maps.normals).contiguous()
    s = bump_scene(maps=replace(maps, normals=ts), settings=RenderSettings(shininess=shininess),
                   lights=scene_lights(direction=((0.0, 0.0, 1.0), (0.0, 0.2, 1.0))))
    fw, bw = finite_render(s)
    n = safe_normalize(torch.tensor([[[1.0, 0.0, 1e-3]]], dtype=F64))
    gc = _gc(_spec_fn(shininess, _lights1), n, torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64), torch.zeros(1, 1, 3, dtype=F64),
             torch.tensor([[0.0, 0.0, 100.0]], dtype=F64), torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64))
    return fw, bw, gc


def case_light_opposite_view():
    """A point light exactly behind the surface point the camera looks at: l = -v, the half vector is 0."""
    s = bump_scene(lights=scene_lights(position=((0.0, 0.0, -100.0), (0.0, 0.0, -300.0))))
    fw, bw = finite_render(s)
    # shading level: directional light along -v exactly; the zero half vector
    n = torch.tensor([[[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]]], dtype=F64)
    p = torch.zeros(1, 2, 3, dtype=F64)
    eye = torch.tensor([[0.0, 0.0, 100.0]], dtype=F64)
    d = torch.tensor([[[0.0, 0.0, -1.0]]], dtype=F64)
    out = specular_reflectance(n, n, p, eye, _lights1(d), 30.0)
    fw &= bool(torch.isfinite(out).all())
    gc = _gc(_spec_fn(30.0, _lights1), n, n, p, eye, d)
    return fw, bw, gc


def case_shininess(shininess: float, per_texel: bool):
    """Shininess 1 .. 1e4, global or a per-texel map."""
    if per_texel:
        s = bump_scene(shininess_map=torch.full((1, 1, 8, 8), shininess, dtype=F64))
    else:
        s = bump_scene(settings=RenderSettings(shininess=shininess))
    fw, bw = finite_render(s)
    # shading level near the lobe's peak, where it is not negligible: N . H = 1 - 1 / s (at least 0.5)
    c = max(1 - 1 / shininess, 0.5)
    n = torch.tensor([[[math.sqrt(1 - c * c), 0.0, c]]], dtype=F64)
    gc = _gc(_spec_fn(shininess, _lights1), n, torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64), torch.zeros(1, 1, 3, dtype=F64),
             torch.tensor([[0.0, 0.0, 100.0]], dtype=F64), torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64))
    return fw, bw, gc


def case_zero_normals(which: str):
    """Zero-length vertex normals / tangents / normal-map texels."""
    s = bump_scene()
    if which == "vertex normals":
        s = replace(s, normals=torch.zeros_like(s.normals))
    elif which == "tangents":
        s = replace(s, tangents=torch.zeros_like(s.tangents))
    else:
        s = replace(s, maps=replace(s.maps, normals=torch.zeros_like(s.maps.normals)))
    fw, bw = finite_render(s)
    z = torch.zeros(2, 3, dtype=F64)
    gc = _gc(safe_normalize, z)
    # at a zero vector safe_normalize's gain is 1 / sqrt(eps) = 1e4: finite differences need a step << 1e-4
    gc &= _gc(lambda a, t, nn: tangent_to_world(a, t, nn), torch.tensor([[0.1, 0.2, 1.0], [0.0, 0.0, 0.0]]),
              torch.tensor([[1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]]), torch.zeros(2, 3), eps=1e-9, atol=1e-4)
    sh = scene_lights().sh
    gc &= _gc(lambda nn: diffuse_irradiance(nn, torch.zeros(1, 2, 3, dtype=F64),
                                            Lights(torch.zeros(1, 3, dtype=F64), torch.zeros(1, 0, 3, dtype=F64),
                                                   torch.zeros(1, 0, 3, dtype=F64), sh=sh), use_sh=True),
              torch.zeros(1, 2, 3))
    return fw, bw, gc


def case_degenerate_triangles(kind: str):
    """Zero-area (repeated vertex, collinear) and sliver triangles added to the mesh."""
    s = bump_scene()
    verts, faces = s.verts.clone(), s.faces
    n = verts.shape[1]
    if kind == "zero-area":
        extra = torch.tensor([[0, 0, 1], [7, 7, 7], [0, 1, 2]])  # vertices 0, 1, 2 are collinear (grid row)
    else:  # a sliver: a vertex 1e-9 mm off the line between two others, and a near-degenerate fan
        extra = torch.tensor([[n, 8, 14], [n, 14, 20]])
        mid = 0.5 * (verts[:, 8] + verts[:, 14]) + torch.tensor([1e-9, 0.0, 0.0], dtype=F64)
        verts = torch.cat([verts, mid[:, None]], 1)
    faces = torch.cat([faces, extra])
    pad = verts.shape[1] - n
    s = replace(s, verts=verts, faces=faces,
                normals=torch.cat([s.normals, s.normals[:, :pad]], 1), tangents=torch.cat([s.tangents, s.tangents[:, :pad]], 1),
                uv=torch.cat([s.uv, s.uv[:pad] + 0.01], 0))
    fw, bw = finite_render(s)
    # barycentrics on a thin (but covering) triangle: smooth, ill-conditioned
    px = torch.tensor([[[2.0, 2.0, 50.0], [2.3, 30.0, 60.0], [2.9, 2.0, 55.0]]], dtype=F64)
    faces1 = torch.tensor([[0, 1, 2]])
    frags = rasterize(px, faces1, 32, 32, cull_backfaces=False)
    gc = len(frags.face) > 0 and _gc(lambda p: barycentrics(p, faces1, frags), px)
    return fw, bw, gc


def case_near_plane(where: str):
    """Part of the mesh nearer than the near plane / all of it behind the camera / a vertex at depth 0."""
    distance = {"crossing near": 20.0, "behind camera": -50.0, "vertex at depth 0": 15.0}[where]
    fw, bw = finite_render(bump_scene(camera=frontal_camera(distance=distance)))
    cam = frontal_camera(distance=100.0)
    pts = torch.tensor([[[1.0, 2.0, 89.0], [3.0, -1.0, 85.0], [-2.0, 4.0, 50.0]]], dtype=F64)  # depths 11, 15, 50 mm
    gc = _gc(lambda p: project(p, cam), pts)
    return fw, bw, gc


def case_face_size(which: str, models_root):
    """The shape model's mean face, all effects, filling a 64^2 image or 10 px wide."""
    from fitme_cli.shape.model import load_shape_model

    sm = load_shape_model(models_root)
    out = sm(*sm.zeros(1))
    out = type(out)(out.vertices.double(), out.normals.double(), out.tangents.double())
    dist, f35 = (200.0, 60.0) if which == "filling the image" else (700.0, 25.0)
    cam = Camera.looking_at_face(1, 64, 64, distance_mm=dist, focal_35mm=f35, dtype=F64)
    s = Scene(out.vertices, out.normals, out.tangents, sm.triangles.long(), sm.uv, procedural_maps(r=32), cam,
              scene_lights(), RenderSettings(shadow_resolution=64))
    img, grads = render_grads(s)
    mask = rasterize(project(out.vertices, cam), sm.triangles.long(), 64, 64).mask
    cols = mask[0].any(0).nonzero()
    width = int(cols.max() - cols.min() + 1)
    ok_size = width == 64 if which == "filling the image" else 8 <= width <= 14
    bad = [k for k, g in grads.items() if g is not None and not torch.isfinite(g).all()]
    return bool(torch.isfinite(img).all()) and ok_size, not bad, None


def case_texture(which: str):
    """All-black maps (albedo 0, specular 0) or saturated ones (albedo 1, specular 1, bright lights)."""
    if which == "black":
        s = bump_scene(maps=procedural_maps(albedo=0.0, specular=0.0))
    else:
        s = bump_scene(maps=procedural_maps(albedo=1.0, specular=1.0), lights=scene_lights(intensity=3.0))
    fw, bw = finite_render(s)
    # the (linear) render is linear in the albedo: gradcheck a tiny render w.r.t. the albedo map
    verts, normals, tangents, faces, uv, _ = bump_mesh(n=4)
    maps = procedural_maps(r=3, albedo=0.0 if which == "black" else 1.0, specular=0.0 if which == "black" else 1.0)
    cam = frontal_camera(size=12, f=15.0)
    r = Renderer(faces, uv, faces, verts.shape[1], RenderSettings())
    lights = scene_lights(intensity=3.0)

    def f(alb):
        return r(verts, normals, tangents, replace(maps, albedo=alb), cam, lights, Effects.all()).linear

    gc = _gc(f, maps.albedo)
    x = torch.tensor([0.0, 1.0, 5.0], dtype=F64, requires_grad=True)  # black, white, over-exposed
    linear_to_srgb(x).sum().backward()
    return fw, bw and bool(torch.isfinite(x.grad).all()), gc


def case_float32_vs_float64():
    """The same scene in float32 and float64: images within 1e-4, gradients within 1e-3 (relative)."""
    i64, g64 = render_grads(bump_scene(dtype=F64), "linear")
    s32 = bump_scene(dtype=torch.float32)
    i32, g32 = render_grads(s32, "linear")
    fw = bool(torch.isfinite(i32).all())
    bw = all(torch.isfinite(g).all() for g in g32.values() if g is not None)
    agree = torch.allclose(i32.double(), i64, atol=1e-4)
    for k, g in g64.items():
        if g is not None and g32[k] is not None:
            scale = float(g.abs().max()) + 1e-6
            agree &= bool(((g32[k].double() - g).abs().max() / scale) < 1e-3)
    return fw, bw, bool(agree)


CASES = {
    "grazing light, N.L = 0 exactly": lambda root: case_grazing_light(True),
    "grazing light, N.L = 1e-9": lambda root: case_grazing_light(False),
    "grazing view, N.V = 0 exactly": lambda root: case_grazing_view(True),
    "grazing view, N.V = 1e-4": lambda root: case_grazing_view(False),
    "N.H ~ 0, shininess 30": lambda root: case_nh_zero_high_shininess(30.0),
    "N.H ~ 0, shininess 1e4": lambda root: case_nh_zero_high_shininess(1e4),
    "light opposite the view (zero half vector)": lambda root: case_light_opposite_view(),
    "shininess 1": lambda root: case_shininess(1.0, False),
    "shininess 1e3": lambda root: case_shininess(1e3, False),
    "shininess 1e4": lambda root: case_shininess(1e4, False),
    "shininess map 1e4": lambda root: case_shininess(1e4, True),
    "zero-length vertex normals": lambda root: case_zero_normals("vertex normals"),
    "zero-length tangents": lambda root: case_zero_normals("tangents"),
    "zero-length normal-map texels": lambda root: case_zero_normals("normal map"),
    "zero-area triangles": lambda root: case_degenerate_triangles("zero-area"),
    "sliver triangles": lambda root: case_degenerate_triangles("sliver"),
    "mesh crossing the near plane": lambda root: case_near_plane("crossing near"),
    "mesh behind the camera": lambda root: case_near_plane("behind camera"),
    "vertex at depth 0": lambda root: case_near_plane("vertex at depth 0"),
    "face filling the image": lambda root: case_face_size("filling the image", root),
    "face 10 px wide": lambda root: case_face_size("10 px wide", root),
    "all-black maps": lambda root: case_texture("black"),
    "saturated maps (albedo 1)": lambda root: case_texture("saturated"),
    "float32 vs float64": lambda root: case_float32_vs_float64(),
}


@pytest.mark.parametrize("name", list(CASES))
def test_stability(name, request):
    root = request.getfixturevalue("models_root") if name.startswith("face ") else None
    forward, backward, gradcheck = CASES[name](root)
    assert forward, "forward not finite (or the scene is not what the case says)"
    assert backward, "backward not finite"
    assert gradcheck in (True, None), "autograd disagrees with finite differences"
