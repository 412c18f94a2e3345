"""``fitme fit``: photos of one person -> an avatar directory (docs/fitting.md, docs/avatar_format.md)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

__all__ = ["command"]


@click.command("fit")
@click.argument("photos", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path), help="Avatar directory to write.")
@click.option("--preset", "preset_name", default="default", show_default=True, type=click.Choice(["fast", "default", "best"]),
              help="Accuracy against time: fast ~15 s, default ~1 min, best a few minutes (one photo, 2 cores).")
@click.option("--iterations", type=click.IntRange(1, 10000), help="Inversion iterations (default: the preset's).")
@click.option("--tune-iterations", type=click.IntRange(0, 1000), help="Tuning iterations (default: the preset's).")
@click.option("--no-tune", is_flag=True, help="Skip tuning the generator.")
@click.option("--render-size", type=click.Choice(["128", "256", "384", "512"]), help="Fitting crop size (default: the preset's).")
@click.option("--effects", default="", help="Force effects on/off, e.g. '+shadows,-specular' (others: chosen per scene).")
@click.option("--noise-gain", type=click.FloatRange(0.0, 1.0), help="Share of BRDF-GAN's fixed noise (fine grain) in the maps: "
              "1 as trained, 0 none (default 0.35: fits the person better; docs/fitting.md).")
@click.option("--device", default="cpu", show_default=True, help="torch device: cpu, cuda, cuda:1.")
@click.option("--seed", default=0, show_default=True)
@click.option("--threads", type=int, help="torch CPU threads (default: all cores).")
@click.option("--force", is_flag=True, help="Replace an existing avatar directory; fit photos that look like different people.")
def command(photos: tuple[Path, ...], out_dir: Path, preset_name: str, iterations: int | None, tune_iterations: int | None,
            no_tune: bool, render_size: str | None, effects: str, noise_gain: float | None, device: str, seed: int,
            threads: int | None, force: bool) -> None:
    """Fit an avatar to PHOTO... (one person): shape, expressions, reflectance maps, cameras and lights.

    Several photos share W and the identity shape; each has its own camera, lights and expression.
    A photo that cannot be used (missing, not an image, no face) is reported and skipped.

    Writes OUT/avatar.json, OUT/params.safetensors, OUT/generator_tuned.safetensors,
    OUT/maps/avatar_{albedo,specular,normals}.{png,exr}, OUT/loss_curve.png and per photo
    OUT/photos/NAME/{panel.png,mesh_camera.obj,landmarks68.json} (docs/avatar_format.md). The directory
    appears complete or not at all.

    \b
    Examples:
      fitme fit photo1.jpg photo2.jpg -o avatar/
      fitme fit selfie.jpg -o avatar/ --preset fast
    """
    import dataclasses
    import hashlib
    import shutil

    import numpy as np
    import torch

    from ..errors import DeviceUnavailable, DifferentPeople, FitmeError, InputNotFound
    from ..fitting.avatar import PhotoRecord, check_output_dir, publish_dir, staging_dir
    from ..fitting.invert import InversionSettings, TuningSettings, invert, prepare_photo, tune
    from ..fitting.outputs import write_avatar
    from ..fitting.presets import preset
    from ..fitting.skin_mask import photo_skin_mask
    from ..io.images import load_image
    from ..perception.detect import DetectSettings, detect
    from ..perception.dlib_resnet import load_dlib_resnet
    from ..perception.registry import ensure_models
    from ..reflectance.gan.store import load_generator, load_w_prior
    from ..render.effects import parse_effects
    from ..shape.facemesh_topology import read_facemesh_topology
    from ..shape.model import load_shape_model
    from ..shape.regions import region_masks
    from .detect import output_names
    from .progress import StageBar, peak_memory_mib

    if threads:
        torch.set_num_threads(threads)
    try:
        forced = parse_effects(effects)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--effects") from None
    dev = _device(device, DeviceUnavailable)
    check_output_dir(out_dir, list(photos), force)
    pre = preset(preset_name)
    iterations = iterations or pre.iterations
    tune_iterations = 0 if no_tune else (pre.tune_iterations if tune_iterations is None else tune_iterations)
    size = int(render_size or pre.render_size)

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    models = ensure_models(["blazeface_short", "blazeface_full", "facemesh", "dlib_resnet", "facenet", "shape_model"])
    topo = read_facemesh_topology()
    prepared, records, descriptors, failures = [], [], [], []
    names = output_names(list(photos), "")
    for path, name in zip(photos, names):
        try:
            img = load_image(path)
            face = detect(img.rgb, DetectSettings()).face  # NoFaceFound when there is none
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        except FitmeError as e:
            click.echo(f"fitme: skipped {path}: {e}", err=True)
            failures.append(e)
            continue
        lm = face.landmarks
        prepared.append(prepare_photo(img.rgb, lm.points[:, :2], lm.ibug68, img.focal_length_35mm, size, 1.6,
                                      lambda c, pts: photo_skin_mask(c, pts, topo.triangles, topo.contours)))
        records.append(PhotoRecord(str(path), digest, tuple(img.rgb.shape[1::-1]), img.focal_length_35mm, name))
        descriptors.append(face.identity)
    if not prepared:
        raise failures[0] if len(failures) == 1 else InputNotFound(f"none of the {len(photos)} photos could be used")
    distance = _max_identity_distance(descriptors)
    if distance > 0.6:  # dlib's same-person threshold
        msg = f"the photos look like different people (identity distance {distance:.2f} > 0.6)"
        if not force:
            raise DifferentPeople(msg + "; pass --force to fit them as one person")
        click.echo(f"fitme: warning: {msg}; fitting anyway (--force)", err=True)
    timings["detect_s"] = time.perf_counter() - t0

    t = time.perf_counter()
    G = load_generator(models).to(dev)
    sm = load_shape_model(models).to(dev)
    desc = load_dlib_resnet(models).to(dev)
    jaw = np.unique(topo.contours["face_oval"])
    timings["load_s"] = time.perf_counter() - t
    inv_s = InversionSettings(iterations=iterations, render_size=size, coarse_fraction=pre.coarse_fraction,
                              coarse_resolution=pre.coarse_resolution, select_effects=pre.select_effects,
                              forced_effects=tuple(forced.items()), seed=seed,
                              noise_gain=InversionSettings.noise_gain if noise_gain is None else noise_gain)
    bar = StageBar(iterations + tune_iterations)
    staging = None
    try:
        t = time.perf_counter()
        inv = invert(prepared, G, sm, desc, sm.landmarks, jaw, inv_s, progress=bar.callback("invert"), device=dev,
                     prior=load_w_prior(models, G))
        timings["invert_s"] = time.perf_counter() - t
        maps, tuned, tune_hist = inv.maps, {}, []
        if tune_iterations:
            t = time.perf_counter()
            mapped = torch.from_numpy(region_masks(sm.region_uv.cpu().numpy().astype(np.uint8), G.settings.resolution)["mapped"])
            tr = tune(prepared, G, inv, sm, desc, sm.landmarks, jaw, mapped, TuningSettings(iterations=tune_iterations),
                      progress=bar.callback("tune"), device=dev)
            maps, tuned, tune_hist = tr.maps, tr.layers, tr.history
            timings["tune_s"] = time.perf_counter() - t
        bar.close()
        t = time.perf_counter()
        staging = staging_dir(out_dir)
        meta = {"settings": {"preset": preset_name, "inversion": _jsonable(dataclasses.asdict(inv_s)),
                             "tune_iterations": tune_iterations, "device": str(dev), "photos_skipped": len(failures)},
                "effects": {"forced": forced},
                "final_losses": {"inversion": inv.history[-1], "tuning": tune_hist[-1] if tune_hist else None},
                "history": {"inversion": inv.history, "tuning": tune_hist}}
        timings["write_s"] = 0.0
        meta["timings"] = timings
        quality = write_avatar(staging, records, prepared, inv, maps, tuned, sm, models, meta)
        timings["write_s"] = time.perf_counter() - t
        timings["total_s"] = time.perf_counter() - t0
        timings["peak_memory_mib"] = peak_memory_mib()
        _rewrite_timings(staging, timings)
        publish_dir(staging, out_dir)
        staging = None
    finally:
        bar.close()
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    stages = ", ".join(f"{k[:-2]} {v:.1f}" for k, v in timings.items() if k.endswith("_s") and k != "total_s")
    click.echo(f"avatar written to {out_dir} in {timings['total_s']:.1f} s ({stages}); "
               f"peak memory {timings['peak_memory_mib']:.0f} MiB")
    for rec, q in zip(records, quality):
        click.echo(f"  {rec.name}: identity similarity {q.identity_similarity:.2f}, landmark error "
                   f"{q.landmark_error_px:.1f} px ({q.landmark_error_pct:.1f} % of the face width)")
    click.echo(f"  effects: {', '.join(inv.effects.on()) or 'none'}")
    if inv.choice is not None:
        for k, why in inv.choice.reasons.items():
            click.echo(f"    {k}: {why}")
    if failures:
        sys.exit(failures[0].exit_code)  # as detect: the avatar is written, the exit code is the first failure's


def _device(name: str, error):
    import torch

    try:
        dev = torch.device(name)
    except RuntimeError:
        raise error(f"unknown device {name!r}; expected cpu, cuda or cuda:N") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise error("--device cuda was asked for, but this torch build or machine has no CUDA device")
    if dev.type not in ("cpu", "cuda"):
        raise error(f"device {name!r} is not supported; expected cpu or cuda")
    return dev


def _max_identity_distance(descriptors) -> float:
    import numpy as np

    d = [np.asarray(x, np.float64) for x in descriptors if x is not None]
    return max((float(np.linalg.norm(a - b)) for i, a in enumerate(d) for b in d[i + 1:]), default=0.0)


def _jsonable(x):
    import json

    return json.loads(json.dumps(x, default=str))


def _rewrite_timings(staging: Path, timings: dict) -> None:
    import json

    from ..io.atomic import atomic_write_bytes

    p = staging / "avatar.json"
    rep = json.loads(p.read_text())
    rep["timings"] = {k: round(v, 2) for k, v in timings.items()}
    atomic_write_bytes(p, (json.dumps(rep, indent=1) + "\n").encode())
