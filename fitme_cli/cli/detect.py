"""``fitme detect``: faces, 468 landmarks, iBUG-68, head pose and identity for each photo."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import click

__all__ = ["command"]


def _check_output_file(path: Path, inputs: list[Path]) -> None:
    from ..errors import OutputNotWritable

    if path.resolve() in {p.resolve() for p in inputs if p.exists()}:
        raise OutputNotWritable("output would overwrite an input photo; choose another path", path)
    if path.is_dir():
        raise OutputNotWritable("output path is a directory; expected a .json file path", path)
    parent = path.resolve().parent
    if not parent.is_dir():
        raise OutputNotWritable(f"output directory {parent} does not exist", path)
    if not os.access(parent, os.W_OK):
        raise OutputNotWritable(f"output directory {parent} is not writable", path)


def _check_output_dir(path: Path) -> None:
    from ..errors import OutputNotWritable

    if path.exists() and not path.is_dir():
        raise OutputNotWritable("--overlay expects a directory, but a file is there", path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputNotWritable(f"cannot create overlay directory: {e.strerror}", path) from None
    if not os.access(path, os.W_OK):
        raise OutputNotWritable("overlay directory is not writable", path)


def output_names(photos: list[Path], suffix: str) -> list[str]:
    """``stem`` + ``suffix`` per photo, numbered where two photos share a stem (also used by ``fit``)."""
    names, seen = [], {}
    for p in photos:
        n = seen.get(p.stem, 0)
        seen[p.stem] = n + 1
        names.append(f"{p.stem}{suffix}" if n == 0 else f"{p.stem}-{n}{suffix}")
    return names


def _summary(path: Path, det) -> str:
    if det.chosen is None:
        return f"{path}: no face"
    f = det.face
    p = f.landmarks.pose
    more = f" (+{len(det.faces) - 1} more)" if len(det.faces) > 1 else ""
    b = f.detection.box
    return (f"{path}: face {b[2] - b[0]:.0f}x{b[3] - b[1]:.0f} px at ({b[0]:.0f}, {b[1]:.0f}), score {f.detection.score:.2f}"
            f"{more}; yaw {p.yaw:+.1f} pitch {p.pitch:+.1f} roll {p.roll:+.1f}")


@click.command("detect")
@click.argument("photos", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write all results to this JSON file.")
@click.option("--overlay", type=click.Path(path_type=Path), help="Write an overlay PNG per photo into this directory.")
@click.option("--all-faces", is_flag=True, help="Landmarks and identity for every face, not only the largest.")
@click.option("--json", "as_json", is_flag=True, help="Print the JSON results to stdout (for pipelines).")
@click.option("--min-face", default=40, show_default=True, type=click.IntRange(8, None), help="Smallest face side to search for, in pixels.")
@click.option("--no-rotations", is_flag=True, help="Do not retry on copies rotated by 90/180/270 degrees.")
@click.option("--threads", default=0, type=click.IntRange(0, None), help="onnxruntime threads (0: its default).")
@click.option("--max-megapixels", default=100, show_default=True, type=click.IntRange(1, 2000),
              help="Refuse larger photos (decompression-bomb guard); raise it for 108/200 MP phone photos.")
def command(photos: tuple[Path, ...], output: Path | None, overlay: Path | None, all_faces: bool,
            as_json: bool, min_face: int, no_rotations: bool, threads: int, max_megapixels: int) -> None:
    """Find faces and landmarks in PHOTOS.

    For each photo: every face's box and score; for the largest face (every face with --all-faces)
    the 468 FaceMesh landmarks in image pixels with relative depth, the iBUG-68 subset, head pose
    (yaw, pitch, roll in degrees) and a 128-d identity descriptor. One bad photo is reported and the
    others still run; the exit status is that of the first failure.

    \b
    Examples:
      fitme detect face.jpg --overlay out/
      fitme detect photos/*.jpg -o faces.json
      fitme detect face.jpg --json | jq '.photos[0].faces[0].pose'
    """
    from tqdm import tqdm

    from ..errors import FitmeError, NoFaceFound
    from ..io import ImageSettings, atomic_write_bytes, atomic_write_image, load_image
    from ..perception.detect import DetectSettings, detect
    from ..perception.registry import ensure_models

    paths = list(photos)
    if output is not None:
        _check_output_file(output, paths)
    if overlay is not None:
        _check_output_dir(overlay)
    settings = DetectSettings(min_face_px=min_face, rotations=not no_rotations, all_faces=all_faces, threads=threads)
    ensure_models(["blazeface_short", "blazeface_full", "facemesh", "dlib_resnet"])
    names = output_names(paths, ".overlay.png")
    inputs = {p.resolve() for p in paths if p.exists()}
    results, first_error = [], None
    bar = tqdm(paths, desc="detect", unit="photo", disable=len(paths) < 2 or None, file=sys.stderr)
    for path, name in zip(bar, names):
        entry: dict = {"path": str(path)}
        try:
            image = load_image(path, ImageSettings(max_pixels=max_megapixels * 1_000_000))
            det = detect(image.rgb, settings)
            entry.update(det.to_json())
            if overlay is not None:
                from ..viz import draw_detection

                target = overlay / name
                if target.resolve() in inputs:
                    raise FitmeError("overlay would overwrite an input photo", target)
                atomic_write_image(target, draw_detection(image.rgb, det))
                entry["overlay"] = str(target)
            if det.chosen is None:
                raise NoFaceFound("no face found" + (" (FaceMesh rejected every candidate)" if det.faces else ""), path)
            if not as_json:
                tqdm.write(_summary(path, det), file=sys.stdout)
        except FitmeError as e:
            if e.path is None:
                e.path = path
            entry["error"] = {"type": type(e).__name__, "code": e.exit_code, "message": e.message}
            tqdm.write(f"fitme: error: {e}", file=sys.stderr)
            first_error = first_error or e
        results.append(entry)
    doc = {"fitme": "detect", "photos": results}
    if output is not None:
        atomic_write_bytes(output, (json.dumps(doc) + "\n").encode())
    if as_json:
        click.echo(json.dumps(doc))
    if first_error is not None:
        sys.exit(first_error.exit_code)
