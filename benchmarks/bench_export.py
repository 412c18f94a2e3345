"""Export time and file sizes per map resolution, and the glTF-Validator's summary (docs/export.md).

    OMP_NUM_THREADS=1 python benchmarks/bench_export.py [AVATAR_DIR] [--out DIR] [--resolutions 1024,2048] [--repeat 2]

Without AVATAR_DIR, fits one to the sample astronaut photo first (`fitme fit --preset fast`, ~20 s).
Exports all formats (glb, gltf, obj) with EXR and PNG maps, the best of ``--repeat`` runs per
resolution, on one torch thread. Prints a markdown table of per-stage seconds and of the files' sizes.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path


def _fit(photo_dir: Path) -> Path:
    from click.testing import CliRunner

    from fitme_cli.cli import main
    from fitme_cli.io.images import write_sample_photo

    photo = write_sample_photo("astronaut", photo_dir / "astronaut.jpg")
    out = photo_dir / "avatar"
    r = CliRunner().invoke(main, ["fit", str(photo), "-o", str(out), "--preset", "fast", "--threads", "1"])
    if r.exit_code:
        sys.exit(f"fit failed: {r.output}")
    return out


def main(argv: list[str]) -> None:
    import torch

    from fitme_cli.export.pipeline import ExportSettings, export_avatar
    from fitme_cli.export.validate import find_validator, validate_gltf
    from fitme_cli.perception.registry import ensure_models
    from fitme_cli.shape.model import load_shape_model

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("avatar", nargs="?", type=Path)
    ap.add_argument("--out", type=Path, help="where to export (default: a temporary directory)")
    ap.add_argument("--resolutions", default="1024,2048")
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="fitme_bench_export."))
    avatar = a.avatar or _fit(tmp)
    out_root = a.out or tmp / "export"
    sm = load_shape_model(ensure_models(["shape_model"]))
    rows, sizes, validator = [], {}, {}
    for res in (int(x) for x in a.resolutions.split(",")):
        best = None
        for _ in range(max(1, a.repeat)):
            t = time.perf_counter()
            r = export_avatar(avatar, out_root / str(res), ExportSettings(formats=("glb", "gltf", "obj"), resolution=res,
                                                                         force=True), sm)
            wall = time.perf_counter() - t
            if best is None or wall < best[0]:
                best = (wall, r)
        wall, r = best
        rows.append((res, r.seconds, wall))
        sizes[res] = r.sizes
        if find_validator():
            validator[res] = {n: validate_gltf(r.files[n]).summary() for n in ("head.glb", "head.gltf")}
    print(f"avatar: {avatar}; mesh: {r.mesh.n_vertices} vertices, {len(r.mesh.faces)} triangles, "
          f"{len(r.mesh.target_names)} morph targets; torch threads: 1\n")
    print("| maps | load s | mesh s | maps s | write s | total s |")
    print("|---:|---:|---:|---:|---:|---:|")
    for res, s, wall in rows:
        print(f"| {res}^2 | {s['load']:.2f} | {s['mesh']:.2f} | {s['maps']:.2f} | {s['write']:.2f} | {wall:.2f} |")
    names = sorted(next(iter(sizes.values())))
    print("\n| file | " + " | ".join(f"{res}^2 (MiB)" for res in sizes) + " |")
    print("|---|" + "---:|" * len(sizes))
    for n in names:
        print(f"| {n} | " + " | ".join(f"{sizes[res][n] / 2**20:.2f}" for res in sizes) + " |")
    print("| **all** | " + " | ".join(f"{sum(sizes[res].values()) / 2**20:.2f}" for res in sizes) + " |")
    if validator:
        print()
        for res, v in validator.items():
            for n, summary in v.items():
                print(f"{res}^2 {n}: {summary}")
    else:
        print("\nglTF-Validator not installed (make verify-export installs it into .cache/npm)")


if __name__ == "__main__":
    main(sys.argv[1:])
