"""Pictures of the shape model for docs/: mean views, random people, +-3 sigma per leading component,
every expression, and the UV region map. Run: .venv/bin/python benchmarks/shape_figures.py"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from fitme_cli.perception.registry import ensure_models
from fitme_cli.shape.model import load_shape_model
from fitme_cli.shape.regions import REGIONS
from fitme_cli.viz.mesh_preview import preview_mesh

OUT = Path(__file__).resolve().parents[1] / "docs"


def _label(img: np.ndarray, text: str) -> np.ndarray:
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _save(name: str, rows: list[list[np.ndarray]]) -> None:
    width = max(len(r) for r in rows)
    blank = np.full_like(rows[0][0], 255)
    grid = np.concatenate([np.concatenate(r + [blank] * (width - len(r)), 1) for r in rows], 0)
    cv2.imwrite(str(OUT / name), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    print(OUT / name)


def main() -> None:
    m = load_shape_model(ensure_models(["shape_model"]))
    t = m.triangles.numpy()
    centre = np.array([0.0, float(m.mean[:, 1].mean()), float(m.mean[:, 2].mean())])
    zeros_e = torch.zeros(1, m.n_expressions)

    def view(ps: torch.Tensor, pe: torch.Tensor, yaw: float, size: int = 220, extent: float = 280.0, c=centre):
        with torch.no_grad():
            v = m.vertices(ps, pe)[0].numpy()
        return preview_mesh(v, t, yaw, size, extent=extent, centre=c)

    ps0, pe0 = m.zeros(1)
    _save("shape_mean.png", [[_label(view(ps0, pe0, yaw, 300), f"mean, yaw {yaw}") for yaw in (0, 45, 90, 180)]])
    g = torch.Generator().manual_seed(1)
    people = m.sample_identity(6, g)
    _save("shape_random_people.png", [[_label(view(people[i : i + 1], zeros_e, yaw), f"p_s ~ N(0, L) #{i}")
                                       for i in range(6)] for yaw in (0, 60)])
    rows = []
    for k in range(4):
        row = []
        for sign in (-3, 3):
            ps = torch.zeros(1, m.n_identity)
            ps[0, k] = sign * m.identity_eigenvalues[k].sqrt()
            row += [_label(view(ps, zeros_e, yaw), f"PC{k + 1} {sign:+d} sd, yaw {yaw}") for yaw in (0, 60)]
        rows.append(row)
    _save("shape_components_3sd.png", rows)
    face_c = np.array([0.0, float(m.mean[:468, 1].mean()), 0.0])
    tiles = []
    for i, name in enumerate(m.expression_names):
        pe = torch.zeros(1, m.n_expressions)
        pe[0, i] = 1.0
        tiles.append(_label(view(ps0, pe, 20, 200, 170.0, face_c), name))
    _save("shape_expressions.png", [tiles[r : r + 9] for r in range(0, len(tiles), 9)])
    palette = np.array([[120, 90, 60], [230, 190, 160], [250, 220, 120], [90, 60, 40], [60, 120, 220],
                        [240, 140, 100], [200, 40, 60], [150, 200, 150]], np.uint8)
    region = m.region_uv.numpy()
    img = np.full(region.shape + (3,), 255, np.uint8)
    img[region < len(REGIONS)] = palette[region[region < len(REGIONS)]]
    for i, name in enumerate(REGIONS):
        cv2.rectangle(img, (6, 6 + 16 * i), (18, 18 + 16 * i), tuple(int(c) for c in palette[i]), -1)
        cv2.putText(img, name, (22, 17 + 16 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(str(OUT / "shape_uv_regions.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    print(OUT / "shape_uv_regions.png")


if __name__ == "__main__":
    main()
