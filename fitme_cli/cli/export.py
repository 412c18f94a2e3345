"""``fitme export``: an avatar directory -> glTF / GLB / OBJ with full-head maps (docs/export.md)."""

from __future__ import annotations

from pathlib import Path

import click

__all__ = ["command"]


def _choices(value: str, allowed: tuple[str, ...], hint: str) -> tuple[str, ...]:
    items = tuple(dict.fromkeys(s.strip().lower() for s in value.split(",") if s.strip()))
    bad = [s for s in items if s not in allowed]
    if bad or not items:
        raise click.BadParameter(f"got {', '.join(bad) or repr(value)}; expected a comma-separated list of {', '.join(allowed)}",
                                 param_hint=hint)
    return items


@click.command("export")
@click.argument("avatar_dir", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path), help="Directory to write into.")
@click.option("--format", "formats", default="glb,obj", show_default=True, help="Any of glb, gltf, obj, comma-separated.")
@click.option("--resolution", default="1024", show_default=True, type=click.Choice(["256", "512", "1024", "2048"]),
              help="Side of the exported maps (the avatar's are 256; larger ones are upsampled).")
@click.option("--maps", "map_formats", default="exr,png", show_default=True,
              help="Standalone map files: exr, png, or both. glTF and OBJ textures are PNG and written when needed.")
@click.option("--expression", default="neutral", show_default=True, type=click.Choice(["neutral", "fitted"]),
              help="The expression the export shows: neutral, or the first photo's fitted one (OBJ: baked in; "
                   "glTF: the default morph weights).")
@click.option("--force", is_flag=True, help="Replace files that exist in the output directory.")
@click.option("--threads", type=int, help="torch CPU threads (default: all cores).")
def command(avatar_dir: Path, out_dir: Path, formats: str, resolution: str, map_formats: str, expression: str,
            force: bool, threads: int | None) -> None:
    """Export AVATAR_DIR (written by `fitme fit`) as a textured full head for other applications.

    Writes into OUT: head.glb (glTF binary, textures embedded), head.gltf + head.bin, head.obj +
    head.mtl, the maps albedo/specular/normals as half-float linear EXR and PNG (albedo sRGB, normals
    16-bit tangent space with OpenGL +Y), and export.json. The mesh is the fitted identity in metres
    (y up, the face toward +z), closed at the eyes and mouth, with normals, UVs and tangents; the glTF
    carries the 52 ARKit expressions as morph targets.

    \b
    Examples:
      fitme export avatar/ -o export/
      fitme export avatar/ -o export/ --format glb,gltf,obj --resolution 2048 --expression fitted
    """
    import torch

    from ..export.pipeline import FORMATS, MAP_FORMATS, ExportSettings, export_avatar

    if threads:
        torch.set_num_threads(threads)
    settings = ExportSettings(formats=_choices(formats, FORMATS, "--format"), maps=_choices(map_formats, MAP_FORMATS, "--maps"),
                              resolution=int(resolution), expression=expression, force=force)
    r = export_avatar(avatar_dir, out_dir, settings)
    click.echo(f"exported {avatar_dir} ({r.expression} expression) to {out_dir} in {r.seconds['total']:.1f} s: "
               f"{r.mesh.n_vertices} vertices, {len(r.mesh.faces)} triangles, {len(r.mesh.target_names)} morph targets, "
               f"{settings.resolution}^2 maps")
    for name in sorted(r.files):
        click.echo(f"  {name:<14} {r.sizes[name] / 2**20:8.2f} MiB")
