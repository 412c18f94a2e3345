"""``fitme fit``: photos of one person -> an avatar directory (first version: inversion + tuning at
fixed settings; presets, the effect selector and the full avatar schema follow, see docs/fitting.md)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click

__all__ = ["command"]

SCHEMA_VERSION = "0.1"


@click.command("fit")
@click.argument("photos", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path), help="Avatar directory to write.")
@click.option("--iterations", default=200, show_default=True, type=click.IntRange(1, 10000), help="Inversion iterations.")
@click.option("--tune-iterations", default=20, show_default=True, type=click.IntRange(0, 1000), help="Tuning iterations (0: no tuning).")
@click.option("--render-size", default=256, show_default=True, type=click.Choice(["128", "256", "512"]), help="Fitting crop size.")
@click.option("--effects", default="", help="Force effects on/off, e.g. '+shadows,-specular' (default: specular and subsurface).")
@click.option("--seed", default=0, show_default=True)
@click.option("--threads", type=int, help="torch CPU threads (default: all cores).")
@click.option("--force", is_flag=True, help="Replace an existing avatar directory's files.")
def command(photos: tuple[Path, ...], out_dir: Path, iterations: int, tune_iterations: int, render_size: str,
            effects: str, seed: int, threads: int | None, force: bool) -> None:
    """Fit an avatar to PHOTO... (one person): shape, expression, reflectance maps, cameras and lights.

    Writes OUT/avatar.json (inputs and their hashes, settings, timings, final losses),
    OUT/params.safetensors (W, p_s, p_e, cameras, lights), OUT/generator_tuned.safetensors (the tuned
    layers), OUT/maps/{albedo,specular,normals}.{png,exr} and, per photo, OUT/NAME.fit.png (crop |
    render | render over the crop).

    \b
    Example:
      fitme fit photo1.jpg photo2.jpg -o avatar/
    """
    import dataclasses
    import hashlib

    import numpy as np
    import torch
    from tqdm import tqdm

    from ..errors import OutputNotWritable
    from ..fitting.invert import InversionSettings, TuningSettings, invert, prepare_photo, tune
    from ..fitting.skin_mask import photo_skin_mask
    from ..io.atomic import atomic_write_bytes, atomic_write_image
    from ..io.images import load_image
    from ..perception.detect import DetectSettings, detect
    from ..perception.dlib_resnet import load_dlib_resnet
    from ..perception.registry import ensure_models
    from ..reflectance.gan.store import load_generator
    from ..render import Effects, Renderer
    from ..render.effects import parse_effects
    from ..shape.facemesh_topology import read_facemesh_topology
    from ..shape.model import load_shape_model
    from ..shape.regions import region_masks

    if threads:
        torch.set_num_threads(threads)
    try:
        forced = parse_effects(effects)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--effects") from None
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputNotWritable("the avatar path exists and is not a directory", out_dir)
    if (out_dir / "avatar.json").exists() and not force:
        raise OutputNotWritable("the directory already holds an avatar; pass --force to replace it", out_dir)
    if out_dir.resolve() in {p.resolve() for p in photos if p.exists()}:
        raise OutputNotWritable("the avatar directory is an input", out_dir)
    try:
        (out_dir / "maps").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputNotWritable(f"cannot create the avatar directory: {e.strerror}", out_dir) from None

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    models = ensure_models(["blazeface_short", "blazeface_full", "facemesh", "dlib_resnet", "shape_model"])
    topo = read_facemesh_topology()
    size = int(render_size)
    prepared, records = [], []
    for path in photos:
        img = load_image(path)
        face = detect(img.rgb, DetectSettings()).face  # NoFaceFound when there is none
        lm = face.landmarks
        prepared.append(prepare_photo(img.rgb, lm.points[:, :2], lm.ibug68, img.focal_length_35mm, size, 1.6,
                                      lambda c, pts: photo_skin_mask(c, pts, topo.triangles, topo.contours)))
        records.append({"path": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                        "size": list(img.rgb.shape[1::-1]), "focal_length_35mm": img.focal_length_35mm})
    timings["detect_s"] = time.perf_counter() - t0

    G = load_generator(models)
    sm = load_shape_model(models)
    desc = load_dlib_resnet(models)
    jaw = np.unique(topo.contours["face_oval"])
    eff = dataclasses.replace(Effects(), **forced)
    inv_s = InversionSettings(iterations=iterations, render_size=size, effects=eff, seed=seed)
    bar = tqdm(total=iterations + tune_iterations, desc="invert", unit="it", file=sys.stderr, disable=None)

    def progress(stage):
        def cb(i, n, rec):
            bar.set_description(stage)
            bar.set_postfix({k: f"{v:.3g}" for k, v in rec.items() if k in ("total", "landmarks", "photometric", "identity")},
                            refresh=False)
            bar.update(1)
        return cb

    t = time.perf_counter()
    inv = invert(prepared, G, sm, desc, sm.landmarks, jaw, inv_s, progress=progress("invert"))
    timings["invert_s"] = time.perf_counter() - t
    maps, tuned, tune_hist = inv.maps, {}, []
    if tune_iterations:
        t = time.perf_counter()
        mapped = torch.from_numpy(region_masks(sm.region_uv.numpy().astype(np.uint8), G.settings.resolution)["mapped"])
        tr = tune(prepared, G, inv, sm, desc, sm.landmarks, jaw, mapped, TuningSettings(iterations=tune_iterations, effects=eff),
                  progress=progress("tune"))
        maps, tuned, tune_hist = tr.maps, tr.layers, tr.history
        timings["tune_s"] = time.perf_counter() - t
    bar.close()

    from safetensors.torch import save_file

    from ..io.atomic import publish_file
    from ..reflectance.skin_data import SkinSample, write_sample

    def save(tensors: dict, name: str) -> None:
        tmp = out_dir / f".{name}.tmp"
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp))
        publish_file(tmp, out_dir / name)

    cam = inv.cameras
    save({"ws": inv.ws, "p_s": inv.p_s, "p_e": inv.p_e, "camera_focal": cam.focal, "camera_principal": cam.principal,
          "camera_rotation": cam.rotation, "camera_translation": cam.translation, "light_ambient": inv.lights.ambient,
          "light_direction": inv.lights.direction, "light_colour": inv.lights.colour}, "params.safetensors")
    if tuned:
        save(tuned, "generator_tuned.safetensors")
    sample = SkinSample(maps.albedo[0].permute(1, 2, 0).numpy(), maps.specular[0, 0].numpy(),
                        maps.normals[0].permute(1, 2, 0).numpy(), {})
    for fmt in ("png", "exr"):
        write_sample(out_dir / "maps", "avatar", sample, fmt)
    renderer = Renderer.for_shape_model(sm)
    with torch.no_grad():
        shp = sm(inv.p_s.expand(len(prepared), -1), inv.p_e)
        out = renderer(shp.vertices, shp.normals, shp.tangents, maps, cam, inv.lights, eff)
    from .detect import output_names

    for i, (p, name) in enumerate(zip(prepared, output_names(list(photos), ".fit.png"))):
        ren = (out.image[i].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
        over = p.crop.copy()
        m = out.mask[i, 0].numpy() > 0
        over[m] = ren[m]
        atomic_write_image(out_dir / name, np.concatenate([p.crop, ren, over], 1))
    timings["total_s"] = time.perf_counter() - t0
    report = {"schema": SCHEMA_VERSION, "inputs": records,
              "settings": {"inversion": json.loads(json.dumps(dataclasses.asdict(inv_s))), "tune_iterations": tune_iterations},
              "effects": {"chosen": eff.on(), "forced": forced},
              "timings": {k: round(v, 2) for k, v in timings.items()},
              "final_losses": {"inversion": inv.history[-1], "tuning": tune_hist[-1] if tune_hist else None},
              "generator": {"resolution": G.settings.resolution}}
    atomic_write_bytes(out_dir / "avatar.json", (json.dumps(report, indent=2) + "\n").encode())
    click.echo(f"avatar written to {out_dir} in {timings['total_s']:.1f} s "
               f"(detect {timings['detect_s']:.1f}, invert {timings['invert_s']:.1f}, tune {timings.get('tune_s', 0):.1f})")
