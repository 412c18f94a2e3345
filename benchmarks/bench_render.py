"""Renderer speed: render + backward of the shape model's head (12.4k vertices, 24.6k triangles) with
512^2 maps, at 256^2 and 512^2 images, with each effect on and off. Prints a Markdown table.

The head fills about 45 % of the image (as a fitting crop does). Timings are medians of 15 runs after 2
warm-ups, torch on all cores; all three maps need gradients (as in tuning). Issue target: all effects at 256^2 in <= 30 ms render + backward.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import torch

from fitme_cli.perception.registry import ensure_models
from fitme_cli.reflectance.maps import ReflectanceMaps
from fitme_cli.render import Camera, Effects, Lights, Renderer
from fitme_cli.shape.model import load_shape_model

CASES = [("none", Effects.none()), ("+specular", Effects(specular=True, subsurface=False)),
         ("+subsurface", Effects(specular=False, subsurface=True)), ("+sh_ambient", Effects(specular=False, subsurface=False, sh_ambient=True)),
         ("+shadows", Effects(specular=False, subsurface=False, shadows=True)),
         ("+multi_light (3)", Effects(specular=False, subsurface=False, multi_light=True)),
         ("default (specular, subsurface)", Effects()), ("all", Effects.all())]


def scene(size: int):
    sm = load_shape_model(ensure_models(["shape_model"]))
    out = sm(*sm.zeros(1))
    g = torch.Generator().manual_seed(0)
    maps = ReflectanceMaps(torch.rand(1, 3, 512, 512, generator=g) * 0.5, torch.rand(1, 1, 512, 512, generator=g) * 0.3,
                           torch.nn.functional.normalize(torch.randn(1, 3, 512, 512, generator=g) * 0.05
                                                         + torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1), dim=1))
    cam = Camera.looking_at_face(1, size, size, distance_mm=450, focal_35mm=60)
    base = Lights.frontal(1)
    dirs = torch.nn.functional.normalize(torch.tensor([[[0.4, 0.5, 1.0], [-0.8, 0.1, 0.5], [0.0, -0.5, 0.8]]]), dim=-1)
    lights = Lights(base.ambient, dirs, torch.tensor([[[0.8] * 3, [0.3] * 3, [0.2] * 3]]), sh=base.sh)
    return sm, Renderer.for_shape_model(sm), out, maps, cam, lights


def time_case(renderer, out, maps, cam, lights, effects, backward: bool) -> float:
    v = out.vertices.detach().requires_grad_(backward)
    n = out.normals.detach().requires_grad_(backward)
    m = ReflectanceMaps(*(x.detach().requires_grad_(backward) for x in (maps.albedo, maps.specular, maps.normals)))
    times = []
    for k in range(17):
        t0 = time.perf_counter()
        o = renderer(v, n, out.tangents.detach(), m, cam, lights, effects)
        if backward:
            o.image.mean().backward()
        if k >= 2:
            times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="256,512")
    args = ap.parse_args()
    warnings.filterwarnings("ignore", category=UserWarning)
    from fitme_cli.ops.memory import retain_freed_memory

    retain_freed_memory()  # as the fitme commands do (fitme_cli/ops/memory.py)
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        sm, r, out, maps, cam, lights = scene(size)
        for name, eff in CASES:
            fwd = time_case(r, out, maps, cam, lights, eff, False)
            both = time_case(r, out, maps, cam, lights, eff, True)
            rows.append((size, name, fwd, both))
    print(f"renderer, {torch.get_num_threads()} threads; ms (median of 15)\n")
    print("| image | effects | forward | forward + backward |")
    print("|---|---|---:|---:|")
    for size, name, fwd, both in rows:
        print(f"| {size}^2 | {name} | {fwd:.1f} | {both:.1f} |")


if __name__ == "__main__":
    main()
