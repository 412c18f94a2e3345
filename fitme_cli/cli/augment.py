"""``fitme augment``: skin-tone augmentation of albedo maps by masked histogram matching."""

from __future__ import annotations

import sys
from pathlib import Path

import click

__all__ = ["command"]

_MAP_TYPES = (".png", ".exr")


@click.command("augment")
@click.argument("in_dir", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path), help="Directory for the augmented maps.")
@click.option("--per-image", default=10, show_default=True, type=click.IntRange(1, 10), help="Monk Skin Tone levels per map (10: all).")
@click.option("--seed", default=0, show_default=True, help="Chooses the levels when fewer than 10.")
def command(in_dir: Path, out_dir: Path, per_image: int, seed: int) -> None:
    """Re-tone every albedo map in IN_DIR (8/16-bit PNG or EXR, fitme's UV layout) to Monk Skin Tone
    levels, keeping brows, lips, hair and stubble as they are. Writes NAME_mstLL.EXT into OUT_DIR in
    the input's size and format; inputs are never touched.

    \b
    Example:
      fitme augment albedos/ -o albedos_mst/ --per-image 3 --seed 1
    """
    import numpy as np
    from safetensors.numpy import load_file
    from tqdm import tqdm

    from ..errors import FitmeError, InputIsDirectory, InputNotFound, OutputNotWritable
    from ..io.maps import read_map, write_map
    from ..perception.registry import ensure_models
    from ..reflectance.augment import augment_albedo
    from ..shape.regions import region_masks

    if not in_dir.exists():
        raise InputNotFound("input directory not found", in_dir)
    if not in_dir.is_dir():
        raise InputIsDirectory("expected a directory of albedo maps, got a file", in_dir)
    if out_dir.resolve() == in_dir.resolve():
        raise OutputNotWritable("output directory is the input directory; choose another so inputs stay untouched", out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputNotWritable(f"cannot create output directory: {e.strerror}", out_dir) from None
    files = sorted(p for p in in_dir.iterdir() if p.is_file() and p.suffix.lower() in _MAP_TYPES)
    if not files:
        raise InputNotFound("no .png or .exr maps in the directory", in_dir)
    region_uv = load_file(str(ensure_models(["shape_model"]) / "shape_model.safetensors"))["region_uv"]
    inputs = {p.resolve() for p in files}
    first_error = None
    written = 0
    bar = tqdm(files, desc="augment", unit="map", disable=None, file=sys.stderr)
    for i, path in enumerate(bar):
        try:
            m = read_map(path)
            masks = region_masks(region_uv, m.linear.shape[0]) if m.linear.shape[0] == m.linear.shape[1] else None
            if masks is None:
                from ..errors import WrongLayout

                raise WrongLayout(f"expected a square UV map, got {m.linear.shape[1]}x{m.linear.shape[0]}", path)
            rng = np.random.default_rng([seed, i])
            levels = sorted(rng.choice(np.arange(1, 11), per_image, replace=False).tolist())
            for level in levels:
                target = out_dir / f"{path.stem}_mst{level:02d}{path.suffix}"
                if target.resolve() in inputs:
                    raise OutputNotWritable("would overwrite an input map", target)
                out, _ = augment_albedo(m.linear, masks["forehead"], masks["mapped"], level)
                write_map(target, out, m.kind)
                written += 1
        except FitmeError as e:
            if e.path is None:
                e.path = path
            tqdm.write(f"fitme: error: {e}", file=sys.stderr)
            first_error = first_error or e
    click.echo(f"{written} maps written to {out_dir}")
    if first_error is not None:
        sys.exit(first_error.exit_code)
