"""MediaPipe FaceMesh's own triangulation and contour groups, read as data from the PyPI package
``mediapipe`` (Apache-2.0): ``mediapipe/tasks/python/vision/face_landmarker.py``.

That file lists ``FACE_LANDMARKS_TESSELATION`` as directed edges, three per triangle in order
(a->b, b->c, c->a): 852 consistently oriented triangles over the 468 landmarks, with holes at the eyes
and the mouth (88 boundary edges: face oval 36, inner lips 20, eyes 16 + 16). We parse the file with
``ast`` and never import mediapipe (its import pulls heavy dependencies we do not need).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass

import numpy as np

from ..errors import ModelBuildError
from ..perception.store import SourceFile

__all__ = ["FaceMeshTopology", "source_file", "read_facemesh_topology"]


def source_file() -> SourceFile:
    from ..perception.registry import MODELS  # the one place that names each model's source package

    return MODELS["shape_model"].source()


@dataclass(frozen=True)
class FaceMeshTopology:
    triangles: np.ndarray  # (852, 3) int64, counter-clockwise seen from the front (outward normals)
    contours: dict[str, np.ndarray]  # name -> (E, 2) int64 edges: lips, left_eye, right_eye, face_oval, ...
    blendshape_names: tuple[str, ...]  # ARKit's 52 names (camelCase): MediaPipe's 51 in its order, then tongueOut


def _camel(name: str) -> str:
    head, *rest = name.lower().split("_")
    return head + "".join(p.capitalize() for p in rest)


def read_facemesh_topology(source: SourceFile | None = None) -> FaceMeshTopology:
    src = source or source_file()
    tree = ast.parse(src.path.read_text())
    groups: dict[str, list[tuple[int, int]]] = {}
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and node.name == "FaceLandmarksConnections":
            for st in node.body:
                if isinstance(st, ast.AnnAssign) and isinstance(st.value, ast.List):
                    groups[st.target.id] = [(c.args[0].value, c.args[1].value) for c in st.value.elts]
        if isinstance(node, ast.ClassDef) and node.name == "Blendshapes":
            for st in node.body:
                if isinstance(st, ast.Assign) and st.targets[0].id != "NEUTRAL":
                    names.append(_camel(st.targets[0].id))
    edges = groups.get("FACE_LANDMARKS_TESSELATION")
    if not edges or len(edges) % 3:
        raise ModelBuildError("no FACE_LANDMARKS_TESSELATION triangle list found", src.path)
    tri = np.array([[edges[3 * i][0], edges[3 * i + 1][0], edges[3 * i + 2][0]] for i in range(len(edges) // 3)])
    chained = all(
        edges[3 * i][1] == edges[3 * i + 1][0] and edges[3 * i + 1][1] == edges[3 * i + 2][0] and edges[3 * i + 2][1] == edges[3 * i][0]
        for i in range(len(edges) // 3)
    )
    if "tongueOut" not in names:  # MediaPipe predicts 51 of ARKit's 52; tongueOut is the missing one
        names.append("tongueOut")
    if not chained or tri.max() != 467 or len(names) != 52:
        raise ModelBuildError("FaceMesh tessellation is not the expected 468-vertex triangle list", src.path)
    contours = {
        k.removeprefix("FACE_LANDMARKS_").lower(): np.asarray(v, np.int64)
        for k, v in groups.items() if k != "FACE_LANDMARKS_TESSELATION"
    }
    return FaceMeshTopology(tri.astype(np.int64), contours, tuple(names))
