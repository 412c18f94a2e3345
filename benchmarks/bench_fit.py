"""`fitme fit` per preset, for one and for three 12 MP photos: wall time per stage, peak memory,
identity similarity (FaceNet, the evaluation network) and landmark error. Prints a Markdown table.

The photos are the astronaut (scikit-image) upscaled onto a 4000 x 3000 canvas, as a phone would
take her portrait; the three-photo set adds a mirrored and a rotated, rescaled copy. Each fit runs in
its own process (`fitme fit`), so peak memory is that fit's. Issue targets on 2 cores: fast <= 15 s,
default <= 60 s, three photos at default <= 120 s, peak memory <= 4 GiB.

    python benchmarks/bench_fit.py [--presets fast,default,best] [--views 1,3] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def phone_photos(out: Path) -> list[Path]:
    from fitme_cli.io.images import sample_photo

    face = sample_photo("astronaut").rgb  # 512 x 512, face ~120 px
    canvas_hw = (3000, 4000)

    def place(img: np.ndarray, scale: float, angle: float, name: str) -> Path:
        big = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        h, w = big.shape[:2]
        m = cv2.getRotationMatrix2D((w / 2, h / 2), angle, 1.0)
        m[:, 2] += [(canvas_hw[1] - w) / 2, (canvas_hw[0] - h) / 2]
        photo = cv2.warpAffine(big, m, canvas_hw[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        p = out / f"{name}.jpg"
        cv2.imwrite(str(p), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
        return p

    return [place(face, 5.5, 0, "phone_a"), place(face[:, ::-1].copy(), 5.0, 0, "phone_b"),
            place(face, 4.5, 8, "phone_c")]


def run(photos: list[Path], preset: str, out: Path, threads: int | None) -> dict:
    cmd = [sys.executable, "-m", "fitme_cli", "fit", *map(str, photos), "-o", str(out), "--preset", preset, "--force"]
    if threads:
        cmd += ["--threads", str(threads)]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"fit failed ({r.returncode}): {r.stderr[-2000:]}")
    rep = json.loads((out / "avatar.json").read_text())
    q = [i["quality"] for i in rep["inputs"]]
    return {"wall_s": wall, **rep["timings"], "identity": float(np.mean([x["identity_similarity"] for x in q])),
            "landmark_px": float(np.mean([x["landmark_error_px"] for x in q])),
            "landmark_pct": float(np.mean([x["landmark_error_pct_face_width"] for x in q])),
            "effects": ",".join(rep["effects"]["chosen"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default="fast,default,best")
    ap.add_argument("--views", default="1,3")
    ap.add_argument("--threads", type=int)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="fitme-bench-fit-"))
    root.mkdir(parents=True, exist_ok=True)
    photos = phone_photos(root)
    rows = []
    for preset in args.presets.split(","):
        for views in (int(v) for v in args.views.split(",")):
            r = run(photos[:views], preset, root / f"{preset}_{views}", args.threads)
            rows.append((preset, views, r))
            print(f"{preset} x{views}: {r['wall_s']:.1f} s", file=sys.stderr)
    print("fitme fit on 12 MP photos (4000 x 3000), 2 cores\n")
    print("| preset | photos | wall s | detect | invert | tune | write | peak MiB | identity sim | landmark px (% face) | effects |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for preset, views, r in rows:
        print(f"| {preset} | {views} | {r['wall_s']:.1f} | {r['detect_s']:.1f} | {r['invert_s']:.1f} | {r.get('tune_s', 0):.1f} | "
              f"{r['write_s']:.1f} | {r['peak_memory_mib']:.0f} | {r['identity']:.2f} | {r['landmark_px']:.1f} ({r['landmark_pct']:.1f}) | {r['effects']} |")


if __name__ == "__main__":
    main()
