"""Golden renders of the shape model's mean face (128 x 128) with deterministic procedural maps (not the
trained GAN), and a labelled contact sheet.

    python benchmarks/render_golden.py            # render, compare with tests/golden/, write docs/render_golden.png
    python benchmarks/render_golden.py --update   # also (re)write tests/golden/*.png

tests/test_render_golden.py renders the same scenes (``golden_scenes``) and compares them with the PNGs.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
GOLDEN_DIR = REPO / "tests" / "golden"
SIZE = 128


def procedural_maps(r: int = 256) -> "ReflectanceMaps":  # noqa: F821
    """Flat albedo (0.5, 0.35, 0.28), specular 0.3, detail normals with a gentle sine bump."""
    from fitme_cli.reflectance.maps import ReflectanceMaps

    u = (torch.arange(r, dtype=torch.float32) + 0.5) / r
    vv, uu = torch.meshgrid(u, u, indexing="ij")
    albedo = torch.tensor([0.5, 0.35, 0.28]).view(1, 3, 1, 1).expand(1, 3, r, r).contiguous()
    spec = torch.full((1, 1, r, r), 0.3)
    k = 2 * math.pi * 24
    n = torch.stack([0.08 * torch.sin(k * uu), 0.08 * torch.sin(k * vv), torch.ones_like(uu)])
    n = torch.nn.functional.normalize(n, dim=0)[None].contiguous()
    return ReflectanceMaps(albedo, spec, n)


def _yaw(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def golden_scenes():
    """name -> (camera, lights, effects, settings). 3/4 view: the head turned 35 degrees (camera yaw)."""
    from fitme_cli.render import Camera, Effects, Lights, RenderSettings
    from fitme_cli.render.camera import frontal_rotation

    front = Camera.looking_at_face(1, SIZE, SIZE, distance_mm=550.0, focal_35mm=50.0)
    r34 = (frontal_rotation(1)[0] @ _yaw(35.0))[None]
    three_q = Camera(front.focal, front.principal, r34, front.translation, SIZE, SIZE)
    key = Lights.frontal(1)
    # key light from the subject's left (+x), a dimmer fill from the right
    two = Lights(torch.full((1, 3), 0.25), torch.nn.functional.normalize(torch.tensor([[[0.8, 0.3, 0.6], [-0.6, 0.0, 0.8]]]), dim=-1),
                 torch.tensor([[[0.9, 0.85, 0.8], [0.25, 0.28, 0.32]]]), sh=key.sh)
    point = Lights(torch.full((1, 3), 0.2), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.tensor([[[1.0, 0.95, 0.9]]]),
                   position=torch.tensor([[[250.0, 250.0, 400.0]]]))
    sh = key.sh.clone()
    sh[:, 3] = 0.25  # brighter from the subject's left (Y_11 ~ x)
    sh_env = Lights(torch.full((1, 3), 0.35), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.zeros(1, 1, 3), sh=sh)
    s = RenderSettings()
    return {
        "front_none": (front, key, Effects.none(), s),
        "front_default": (front, key, Effects(), s),
        "front_all_two_lights": (front, two, Effects.all(), s),
        "threequarter_default": (three_q, two, Effects(), s),
        "front_point_light": (front, point, Effects(specular=True, subsurface=True), s),
        "threequarter_sh_ambient": (three_q, sh_env, Effects(specular=False, subsurface=True, sh_ambient=True), s),
    }


def render_all(models_root: Path) -> dict[str, np.ndarray]:
    """name -> (H, W, 3) float sRGB in [0, 1]."""
    from fitme_cli.render import Renderer
    from fitme_cli.shape.model import load_shape_model

    sm = load_shape_model(models_root)
    out = sm(*sm.zeros(1))
    renderer = Renderer.for_shape_model(sm)
    maps = procedural_maps()
    res = {}
    with torch.no_grad():
        for name, (cam, lights, effects, settings) in golden_scenes().items():
            renderer.settings = settings
            img = renderer(out.vertices, out.normals, out.tangents, maps, cam, lights, effects).image
            res[name] = img[0].permute(1, 2, 0).numpy().astype(np.float64)
    return res


def to_png(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


def contact_sheet(images: dict[str, np.ndarray], path: Path, scale: int = 2) -> None:
    from PIL import Image, ImageDraw

    names = list(images)
    cols = 3
    rows = math.ceil(len(names) / cols)
    cell = SIZE * scale
    sheet = Image.new("RGB", (cols * cell, rows * (cell + 16)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, name in enumerate(names):
        x, y = (k % cols) * cell, (k // cols) * (cell + 16)
        sheet.paste(Image.fromarray(to_png(images[name])).resize((cell, cell), Image.NEAREST), (x, y + 16))
        draw.text((x + 4, y + 2), name, fill=(0, 0, 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)


def compare(img: np.ndarray, golden_png: Path) -> tuple[float, float]:
    """(mean, max) absolute difference in [0, 1] units between a float image and a stored PNG."""
    from PIL import Image

    ref = np.asarray(Image.open(golden_png).convert("RGB"), dtype=np.float64) / 255
    d = np.abs(img - ref)
    return float(d.mean()), float(d.max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--update", action="store_true", help="rewrite tests/golden/*.png")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from PIL import Image

    from fitme_cli.perception.registry import ensure_models

    images = render_all(ensure_models(["blazeface_short", "blazeface_full", "facemesh"]))
    GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    worst = 0.0
    for name, img in images.items():
        path = GOLDEN_DIR / f"{name}.png"
        if args.update or not path.exists():
            Image.fromarray(to_png(img)).save(path, optimize=True)
        mean, mx = compare(img, path)
        worst = max(worst, mx)
        print(f"{name:28s} mean |diff| {mean * 255:.3f}/255  max {mx * 255:.1f}/255")
    contact_sheet(images, REPO / "docs" / "render_golden.png")
    print(f"contact sheet: {REPO / 'docs' / 'render_golden.png'}")
    return 0 if worst < 8 / 255 else 1


if __name__ == "__main__":
    sys.exit(main())
