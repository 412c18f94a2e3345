"""``fitme render``: relight an avatar in preset environments on a turntable; a contact sheet PNG."""

from __future__ import annotations

from pathlib import Path

import click

__all__ = ["command"]


@click.command("render")
@click.argument("avatar_dir", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_path", required=True, type=click.Path(path_type=Path), help="Contact sheet image (.png or .jpg).")
@click.option("--env", "envs", default="studio,outdoor,sunset,dramatic", show_default=True,
              help="Environments, comma-separated: studio, outdoor, sunset, dramatic, night, photo (the lights "
                   "fitted to the first photo), or all.")
@click.option("--light", "lights", multiple=True, metavar="AZ,EL[,I]",
              help="Add a row lit by this white directional light: azimuth and elevation in degrees (0,0 = from "
                   "the camera; +azimuth from the viewer's right), intensity (default 1). Repeat for more lights.")
@click.option("--expression", default="neutral", show_default=True,
              help="neutral, fitted (the first photo's), or ARKit weights such as jawOpen=0.5,mouthSmileLeft=0.3.")
@click.option("--turntable", default=6, show_default=True, type=click.IntRange(1, 36),
              help="Views per environment, evenly around the full turn, starting frontal.")
@click.option("--size", default=256, show_default=True, type=click.IntRange(64, 1024), help="Side of each view in pixels.")
@click.option("--no-labels", is_flag=True, help="Do not write environment names and yaws on the sheet.")
@click.option("--force", is_flag=True, help="Replace an existing output file.")
@click.option("--threads", type=int, help="torch CPU threads (default: all cores).")
def command(avatar_dir: Path, out_path: Path, envs: str, lights: tuple[str, ...], expression: str, turntable: int,
            size: int, no_labels: bool, force: bool, threads: int | None) -> None:
    """Relight AVATAR_DIR (written by `fitme fit`) with fitme's renderer and write a contact sheet:
    one row per environment, one column per turntable view.

    \b
    Examples:
      fitme render avatar/ -o sheet.png
      fitme render avatar/ -o sheet.png --env studio,photo --turntable 8 --expression jawOpen=0.4
      fitme render avatar/ -o sheet.png --env sunset --light 60,30,1.5
    """
    import time

    import torch

    from ..export.pipeline import check_output_file
    from ..export.render import SheetSettings, parse_environments, parse_expression, parse_light, render_sheet
    from ..export.source import load_source
    from ..fitting.avatar import check_shape_model
    from ..io.atomic import atomic_write_image
    from ..perception.registry import ensure_models
    from ..shape.model import load_shape_model

    if threads:
        torch.set_num_threads(threads)
    try:
        env_names = parse_environments(envs)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--env") from None
    try:
        custom = tuple(parse_light(s) for s in lights)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--light") from None
    if out_path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise click.BadParameter(f"{out_path.name}: expected a .png or .jpg file name", param_hint="--output")
    t0 = time.perf_counter()
    source = load_source(avatar_dir)
    check_output_file(out_path, avatar_dir, force)
    sm = load_shape_model(ensure_models(["shape_model"]))
    check_shape_model(avatar_dir, source.p_s, source.p_e, source.fitted_vertices, sm)
    try:
        weights = parse_expression(expression, sm.expression_names, source.p_e[0])
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--expression") from None
    settings = SheetSettings(environments=env_names, custom_lights=custom, turntable=turntable, size=size,
                             weights=tuple(float(w) for w in weights), labels=not no_labels)
    sheet, rows, yaws = render_sheet(source, sm, settings)
    atomic_write_image(out_path, sheet)
    click.echo(f"wrote {out_path} ({sheet.shape[1]}x{sheet.shape[0]}) in {time.perf_counter() - t0:.1f} s: "
               f"{len(rows)} environments ({', '.join(rows)}) x {len(yaws)} views")
