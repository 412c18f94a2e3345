"""``fitme tune``: run or continue the tuning stage on an existing avatar directory."""

from __future__ import annotations

import time
from pathlib import Path

import click

__all__ = ["command"]


@click.command("tune")
@click.argument("avatar_dir", type=click.Path(path_type=Path))
@click.option("--iterations", default=20, show_default=True, type=click.IntRange(1, 1000), help="Tuning iterations to add.")
@click.option("--device", default="cpu", show_default=True, help="torch device: cpu, cuda, cuda:1.")
@click.option("--threads", type=int, help="torch CPU threads (default: all cores).")
def command(avatar_dir: Path, iterations: int, device: str, threads: int | None) -> None:
    """Tune the generator's 4 middle layers of AVATAR_DIR (written by `fitme fit`) for more iterations,
    starting from its tuned layers when it has them. W, shape, cameras and lights stay as fitted.

    Everything needed is inside the directory; the photos need not be where they were. The directory
    is replaced atomically: a kill leaves the old avatar.

    \b
    Example:
      fitme tune avatar/ --iterations 30
    """
    import dataclasses
    import shutil

    import numpy as np
    import torch

    from ..errors import AvatarInvalid, DeviceUnavailable
    from ..fitting.avatar import check_generator, check_shape_model, load_avatar, publish_dir, staging_dir
    from ..fitting.invert import TuningSettings, tune
    from ..fitting.outputs import write_avatar
    from ..perception.dlib_resnet import load_dlib_resnet
    from ..perception.registry import ensure_models
    from ..reflectance.gan.store import load_generator
    from ..shape.facemesh_topology import read_facemesh_topology
    from ..shape.model import load_shape_model
    from ..shape.regions import region_masks
    from .fit import _device
    from .progress import StageBar, peak_memory_mib

    if threads:
        torch.set_num_threads(threads)
    dev = _device(device, DeviceUnavailable)
    t0 = time.perf_counter()
    av = load_avatar(avatar_dir)
    models = ensure_models(["dlib_resnet", "facenet", "shape_model"])
    G = load_generator(models)
    from ..reflectance.gan.networks import decode_maps

    with torch.no_grad():  # the inverted maps, before any tuning: the chromaticity loss's reference
        inverted = decode_maps(G.synthesis(av.inversion.ws, noise_mode="const", noise_gain=av.inversion.noise_gain), G.settings)
    if av.tuned:
        names = dict(G.named_parameters())
        unknown = [k for k in av.tuned if k not in names or names[k].shape != av.tuned[k].shape]
        if unknown:
            raise AvatarInvalid(f"tuned layers do not fit the shipped generator: {', '.join(unknown[:3])}", avatar_dir)
        G.load_state_dict(av.tuned, strict=False)
        with torch.no_grad():
            held = decode_maps(G.synthesis(av.inversion.ws, noise_mode="const", noise_gain=av.inversion.noise_gain), G.settings)
    else:
        held = inverted
    check_generator(avatar_dir, held.albedo)  # W means another texture under another BRDF-GAN
    G = G.to(dev)
    sm = load_shape_model(models)
    check_shape_model(avatar_dir, av.inversion.p_s, av.inversion.p_e, av.fitted_vertices, sm)
    sm = sm.to(dev)
    desc = load_dlib_resnet(models).to(dev)
    topo = read_facemesh_topology()
    jaw = np.unique(topo.contours["face_oval"])
    mapped = torch.from_numpy(region_masks(sm.region_uv.cpu().numpy().astype(np.uint8), G.settings.resolution)["mapped"])
    rep = av.report
    before = rep.get("history", {}).get("tuning", [])
    bar = StageBar(iterations)
    staging = None
    try:
        t = time.perf_counter()
        inv = dataclasses.replace(av.inversion, maps=inverted)
        tr = tune(av.photos, G, inv, sm, desc, sm.landmarks, jaw, mapped, TuningSettings(iterations=iterations),
                  progress=bar.callback("tune"), device=dev)
        bar.close()
        tune_s = time.perf_counter() - t
        timings = dict(rep.get("timings", {}))
        timings["tune_s"] = round(timings.get("tune_s", 0.0) + tune_s, 2)
        history = {"inversion": rep.get("history", {}).get("inversion", []), "tuning": before + tr.history}
        settings = dict(rep.get("settings", {}))
        settings["tune_iterations"] = settings.get("tune_iterations", 0) + iterations
        meta = {"settings": settings, "effects": rep.get("effects", {}),
                "final_losses": {"inversion": (rep.get("final_losses") or {}).get("inversion"), "tuning": tr.history[-1]},
                "history": history, "timings": timings}
        staging = staging_dir(avatar_dir)
        quality = write_avatar(staging, av.records, av.photos, inv, tr.maps, tr.layers, sm, models, meta)
        publish_dir(staging, avatar_dir)
        staging = None
    finally:
        bar.close()
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    click.echo(f"tuned {avatar_dir} by {iterations} iterations in {time.perf_counter() - t0:.1f} s "
               f"(tune {tune_s:.1f}); peak memory {peak_memory_mib():.0f} MiB")
    for rec, q in zip(av.records, quality):
        click.echo(f"  {rec.name}: identity similarity {q.identity_similarity:.2f}")
