"""``fitme dataset``: procedural facial reflectance maps (diffuse, specular, normals) for BRDF-GAN training."""

from __future__ import annotations

import sys
from pathlib import Path

import click

__all__ = ["command"]

_WORKER = {}


def _init_worker(models: str, settings) -> None:
    from ..reflectance.skin_data import skin_layout

    _WORKER["layout"] = skin_layout(models, settings.size)
    _WORKER["settings"] = settings


def _job(args):
    """Generate and write sample ``index``; returns (params, MapStats)."""
    from ..reflectance.skin_data import MapStats, generate_sample, write_sample

    out_dir, seed, index, fmt = args
    layout, settings = _WORKER["layout"], _WORKER["settings"]
    sample = generate_sample(layout, seed, index, settings)
    write_sample(out_dir, f"sample_{index:05d}", sample, fmt)
    st = MapStats()
    st.add(sample, layout.masks["mapped"])
    return sample.params, st


@click.command("dataset")
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("-n", "count", required=True, type=click.IntRange(1, 1_000_000), help="Number of samples.")
@click.option("--size", default=512, show_default=True, type=click.IntRange(64, 4096), help="Map side in texels (a power of two).")
@click.option("--seed", default=0, show_default=True, type=int, help="Samples are a function of (seed, index) only.")
@click.option("--format", "fmt", default="png", show_default=True, type=click.Choice(["png", "exr"]),
              help="png: 8-bit sRGB albedo, 8-bit linear specular, 16-bit normals; exr: linear half floats.")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(1, 64), help="Processes.")
@click.option("--force", is_flag=True, help="Overwrite a dataset already in OUT_DIR.")
def command(out_dir: Path, count: int, size: int, seed: int, fmt: str, workers: int, force: bool) -> None:
    """Write COUNT procedural facial reflectance samples into OUT_DIR, in fitme's UV layout:
    sample_NNNNN_{albedo,specular,normals}.{png,exr}, plus dataset.json (settings, seed, per-sample
    parameters and map statistics). Normals are tangent space (+x = u, +y = v up, +z out) stored as
    n * 0.5 + 0.5.

    \b
    Example:
      fitme dataset data/skin -n 2000 --size 256 --seed 0
    """
    import json

    from tqdm import tqdm

    from ..errors import OutputNotWritable
    from ..io.atomic import atomic_write_bytes
    from ..perception.registry import ensure_models
    from ..reflectance.skin_data import MapStats, SkinDataSettings, settings_dict

    try:
        settings = SkinDataSettings(size=size)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--size") from None
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputNotWritable("output path exists and is not a directory", out_dir)
    if out_dir.is_dir() and not force:
        existing = [p for p in out_dir.iterdir() if p.name == "dataset.json" or (p.name.startswith("sample_") and p.suffix in (".png", ".exr"))]
        if existing:
            raise OutputNotWritable(f"already contains a dataset ({existing[0].name}, ...); use --force to overwrite", out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".fitme_write_probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise OutputNotWritable(f"cannot write here: {e.strerror or e}", out_dir) from None
    models = str(ensure_models(["shape_model"]))
    jobs = [(str(out_dir), seed, i, fmt) for i in range(count)]
    stats = MapStats()
    params = []
    bar = tqdm(total=count, desc="dataset", unit="sample", disable=None, file=sys.stderr)
    try:
        if workers == 1:
            _init_worker(models, settings)
            results = map(_job, jobs)
            for p, st in results:
                params.append(p)
                stats.merge(st)
                bar.update()
        else:
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(models, settings)) as ex:
                for p, st in ex.map(_job, jobs, chunksize=4):
                    params.append(p)
                    stats.merge(st)
                    bar.update()
    finally:
        bar.close()
    summary = stats.summary()
    meta = {
        "generator": "fitme_cli.reflectance.skin_data",
        "seed": seed,
        "count": count,
        "format": fmt,
        "settings": settings_dict(settings),
        "layout": "fitme shape model UV (row 0 = v = 1)",
        "encoding": {"albedo": "linear diffuse albedo" + (" (sRGB-encoded 8-bit PNG)" if fmt == "png" else ""),
                     "specular": "linear specular albedo" + (" (8-bit, not gamma-encoded)" if fmt == "png" else ""),
                     "normals": "tangent space n * 0.5 + 0.5 (+x = u, +y = v up, +z out)" + (" (16-bit, not gamma-encoded)" if fmt == "png" else "")},
        "stats": summary,
        "samples": [{"name": f"sample_{p['index']:05d}", "params": p} for p in params],
    }
    atomic_write_bytes(out_dir / "dataset.json", (json.dumps(meta, indent=1) + "\n").encode())
    click.echo(f"{count} samples written to {out_dir} (albedo mean {summary['albedo_mean']:.3f} std {summary['albedo_std']:.3f}; "
               f"normals mean {summary['normals_mean']:.3f} std {summary['normals_std']:.3f})")
