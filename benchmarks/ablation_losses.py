"""Ablation of the inversion's losses on synthetic subjects with ground truth (the paper's Fig. 7 as a
table): the full fit, then each loss removed (its lambda set to 0). Prints a Markdown table of the
mean over subjects: landmark error (px), identity-shape error (mm, point to surface after rigid
alignment), albedo error (ΔE after a per-channel gain, the light/albedo scale being ambiguous) and
identity similarity of photo and render by the evaluation network (FaceNet).

    python benchmarks/ablation_losses.py [--seeds 0,2] [--iterations 60] [--size 128]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

LOSSES = ("landmarks", "photometric", "identity", "perceptual", "w", "shape", "expression")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,2")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args()

    from fitme_cli.fitting.invert import InversionSettings, invert, prepare_photo
    from fitme_cli.fitting.metrics import evaluate_fit
    from fitme_cli.fitting.presets import preset
    from fitme_cli.fitting.skin_mask import photo_skin_mask
    from fitme_cli.fitting.synthetic import SyntheticSettings, make_subject
    from fitme_cli.perception.detect import DetectSettings, detect
    from fitme_cli.perception.dlib_resnet import load_dlib_resnet
    from fitme_cli.perception.facenet import facenet_embedding_onnx
    from fitme_cli.perception.registry import ensure_models
    from fitme_cli.reflectance.gan.store import load_generator, load_w_prior
    from fitme_cli.render import Renderer
    from fitme_cli.render.shading import srgb_to_linear
    from fitme_cli.shape.facemesh_topology import read_facemesh_topology
    from fitme_cli.shape.model import load_shape_model

    models = ensure_models(["blazeface_short", "blazeface_full", "facemesh", "dlib_resnet", "facenet", "shape_model"])
    sm, desc, topo = load_shape_model(models), load_dlib_resnet(models), read_facemesh_topology()
    renderer = Renderer.for_shape_model(sm)
    jaw = np.unique(topo.contours["face_oval"])
    pre = preset("fast")
    base = InversionSettings().lambdas
    variants = {"full": base} | {f"no {k}": tuple(0.0 if i == j else v for j, v in enumerate(base)) for i, k in enumerate(LOSSES)}
    rows: dict[str, list] = {k: [] for k in variants}
    for seed in (int(s) for s in args.seeds.split(",")):
        G0 = load_generator(models)
        subject = make_subject(G0, sm, renderer, SyntheticSettings(n_views=1, seed=seed))
        photo = subject.photos[0]
        lm = detect(photo, DetectSettings(identity=False)).face.landmarks
        p = prepare_photo(photo, lm.points[:, :2], lm.ibug68, subject.settings.focal_35mm, args.size, 1.6,
                          lambda c, pts: photo_skin_mask(c, pts, topo.triangles, topo.contours))
        e_photo = facenet_embedding_onnx(p.crop, p.ibug68, models)
        for name, lam in variants.items():
            G = load_generator(models)
            s = InversionSettings(iterations=args.iterations, render_size=args.size, coarse_fraction=pre.coarse_fraction,
                                  coarse_resolution=pre.coarse_resolution, select_effects=False, lambdas=lam)
            t = time.perf_counter()
            res = invert([p], G, sm, desc, sm.landmarks, jaw, s, prior=load_w_prior(models, G))
            secs = time.perf_counter() - t
            rep = evaluate_fit(subject, sm, res.p_s, res.p_e, res.cameras, res.maps, [p.to_photo])
            with torch.no_grad():
                shp = sm(res.p_s, res.p_e)
                bg = srgb_to_linear(torch.from_numpy(p.crop).permute(2, 0, 1)[None].float() / 255)
                out = renderer(shp.vertices, shp.normals, shp.tangents, res.maps, res.cameras, res.lights, res.effects,
                               background=bg)
            img = (out.image[0].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
            sim = float(np.dot(e_photo, facenet_embedding_onnx(img, p.ibug68, models)))
            rows[name].append((rep.landmark_px, rep.shape.mean_mm, rep.albedo.delta_e_gain, sim, secs))
            print(f"seed {seed} {name}: {rows[name][-1]}", file=sys.stderr)
    print(f"Loss ablation: synthetic subjects (seeds {args.seeds}), one view, {args.iterations} iterations at "
          f"{args.size}^2 (fast-preset schedule), mean over subjects\n")
    print("| variant | landmarks px | identity shape mm | albedo ΔE (gain) | identity sim | s |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, r in rows.items():
        a = np.array(r)
        print(f"| {name} | {a[:, 0].mean():.2f} | {a[:, 1].mean():.3f} | {a[:, 2].mean():.2f} | {a[:, 3].mean():.3f} | {a[:, 4].mean():.0f} |")


if __name__ == "__main__":
    main()
