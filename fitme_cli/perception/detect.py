"""Find faces and their landmarks in a photo: BlazeFace (short + full range, tiled for small faces,
re-run on rotated copies), then FaceMesh on the chosen face(s), iBUG-68 subset, head pose, identity.

All networks run through onnxruntime. Coordinates are image pixels of the upright (EXIF-applied) photo,
x right, y down.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import NoFaceFound
from .blazeface import FULL_RANGE, SHORT_RANGE, AnchorSpec, RawDetections, decode, iou, ssd_anchors, weighted_nms
from .facemesh import IBUG68_FROM_FACEMESH, Roi, crop, landmarks_to_image, roi_from_detection, roi_from_landmarks
from .head_pose import HeadPose, head_pose
from .onnx_runner import onnx_session
from .registry import ensure_models

__all__ = ["DetectSettings", "FaceBox", "FaceLandmarks", "Face", "Detection", "detect_faces", "detect"]

_TILE_BATCH = 16


@dataclass(frozen=True)
class DetectSettings:
    min_face_px: int = 40  # smallest face side to look for; smaller means more tiles
    score_threshold: float = 0.5  # BlazeFace, as MediaPipe
    iou_threshold: float = 0.3  # weighted NMS, as MediaPipe
    rotations: bool = True  # retry on copies rotated by 90, 270, 180 degrees when nothing is found upright
    all_faces: bool = False  # landmarks and identity for every face, not only the chosen one
    exhaustive: bool = False  # search every tile scale even after a coarser one found a face
    landmark_passes: int = 2  # FaceMesh passes; later ones re-centre on the previous landmarks
    min_presence: float = 0.5  # FaceMesh face-presence probability below which landmarks are rejected
    identity: bool = True  # compute the dlib identity descriptor
    threads: int = 0  # onnxruntime intra-op threads, 0 = its default

    def __post_init__(self) -> None:
        if self.min_face_px < 8:
            raise ValueError(f"min_face_px must be >= 8, got {self.min_face_px}")
        if self.landmark_passes < 1:
            raise ValueError(f"landmark_passes must be >= 1, got {self.landmark_passes}")


@dataclass(frozen=True)
class FaceBox:
    box: np.ndarray  # (4,) float32 x0, y0, x1, y1, image px
    keypoints: np.ndarray  # (6, 2) float32 image px: eyes, nose tip, mouth, tragions
    score: float  # [0, 1]
    rotation: int  # degrees (0, 90, 180, 270, counter-clockwise) of the copy it was found in
    presence: float  # FaceMesh's face-presence probability on this box, the false-positive filter

    @property
    def area(self) -> float:
        return float(max(self.box[2] - self.box[0], 0) * max(self.box[3] - self.box[1], 0))


@dataclass(frozen=True)
class FaceLandmarks:
    points: np.ndarray  # (468, 3) float32 image px; z relative depth in px, smaller = nearer
    ibug68: np.ndarray  # (68, 2) float32 image px, iBUG order
    presence: float  # FaceMesh face-presence probability
    pose: HeadPose
    roi: Roi


@dataclass(frozen=True)
class Face:
    detection: FaceBox
    landmarks: FaceLandmarks | None = None
    identity: np.ndarray | None = None  # (128,) float32 dlib descriptor


@dataclass(frozen=True)
class Detection:
    width: int
    height: int
    faces: tuple[Face, ...]  # sorted by box area, largest first
    chosen: int | None  # index into faces of the face with landmarks, None when no face
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def face(self) -> Face:
        if self.chosen is None:
            raise NoFaceFound("no face found")
        return self.faces[self.chosen]

    def to_json(self) -> dict:
        """Plain JSON-able data: lists of floats, image pixels, degrees."""

        def r(a: np.ndarray, nd: int = 2) -> list:
            return np.round(np.asarray(a, np.float64), nd).tolist()

        faces = []
        for f in self.faces:
            d = {"box": r(f.detection.box), "score": round(f.detection.score, 4),
                 "keypoints": r(f.detection.keypoints), "rotation": f.detection.rotation,
                 "presence": round(f.detection.presence, 4)}
            if f.landmarks is not None:
                lm = f.landmarks
                d["landmarks"] = r(lm.points)
                d["ibug68"] = r(lm.ibug68)
                d["pose"] = {"yaw": round(lm.pose.yaw, 2), "pitch": round(lm.pose.pitch, 2), "roll": round(lm.pose.roll, 2)}
            if f.identity is not None:
                d["identity"] = r(f.identity, 5)
            faces.append(d)
        return {"width": self.width, "height": self.height, "chosen": self.chosen, "faces": faces,
                "seconds": {k: round(v, 4) for k, v in self.seconds.items()}}


# ---------------------------------------------------------------- detection


def _window(image: np.ndarray, x0: int, y0: int, side: int, n: int) -> np.ndarray:
    """The square window [x0, x0+side) x [y0, y0+side) of image, black outside, resized to n x n."""
    h, w = image.shape[:2]
    out = np.zeros((side, side, 3), np.uint8)
    xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + side, w), min(y0 + side, h)
    if xb > xa and yb > ya:
        out[ya - y0 : yb - y0, xa - x0 : xb - x0] = image[ya:yb, xa:xb]
    interp = cv2.INTER_AREA if side > n else cv2.INTER_LINEAR
    return cv2.resize(out, (n, n), interpolation=interp)


def _unrotate_unit(points: np.ndarray, k: int) -> np.ndarray:
    """Map (..., 2) points in [0, 1]² of np.rot90(square, k) back to the square."""
    p = points.copy()
    for _ in range(k % 4):  # one rot90 step maps (u, v) to (v, 1 - u); undo it
        u, v = p[..., 0].copy(), p[..., 1].copy()
        p[..., 0], p[..., 1] = 1.0 - v, u
    return p


def _run_detector(
    image: np.ndarray, windows: list[tuple[int, int, int]], name: str, spec: AnchorSpec, root: Path,
    s: DetectSettings, rotations: tuple[int, ...],
) -> dict[int, RawDetections]:
    """Candidates scoring at least the threshold (before NMS), per rotation, in image pixels.

    Each window is cut and resized once, then seen by the network in every rotation. Network outputs
    are continuous window coordinates; we shift by half a pixel to the pixel-centre convention that cv2
    and FaceMesh use (pixel i's centre at i).
    """
    sess = onnx_session(root / f"{name}.onnx", s.threads)
    anchors = ssd_anchors(spec)
    n = spec.input_size
    jobs = [(win, k) for win in windows for k in rotations]
    out: dict[int, list[RawDetections]] = {k: [] for k in rotations}
    for i in range(0, len(jobs), _TILE_BATCH):
        chunk = jobs[i : i + _TILE_BATCH]
        cache: dict[tuple[int, int, int], np.ndarray] = {}
        batch = []
        for win, k in chunk:
            if win not in cache:
                cache[win] = _window(image, *win, n)
            batch.append(np.rot90(cache[win], k))
        x = (np.stack(batch).astype(np.float32) / 127.5 - 1.0).transpose(0, 3, 1, 2)
        reg, logit = sess.run(None, {"image": np.ascontiguousarray(x)})
        for ((x0, y0, side), k), r, l in zip(chunk, reg, logit):
            d = decode(r, l, spec, anchors)
            keep = d.scores >= s.score_threshold
            if not keep.any():
                continue
            off = np.array([x0, y0], np.float32) - 0.5
            corners = _unrotate_unit(d.boxes[keep].reshape(-1, 2, 2), k)
            boxes = np.concatenate([corners.min(1), corners.max(1)], axis=1) * side + np.tile(off, 2)
            kps = _unrotate_unit(d.keypoints[keep], k) * side + off
            out[k].append(RawDetections(boxes.astype(np.float32), kps.astype(np.float32), d.scores[keep]))
    return {k: _concat(v) for k, v in out.items()}


def _concat(parts: list[RawDetections]) -> RawDetections:
    if not parts:
        return RawDetections(np.zeros((0, 4), np.float32), np.zeros((0, 6, 2), np.float32), np.zeros(0, np.float32))
    return RawDetections(
        np.concatenate([p.boxes for p in parts]),
        np.concatenate([p.keypoints for p in parts]),
        np.concatenate([p.scores for p in parts]),
    )


def _tiles(w: int, h: int, side: int) -> list[tuple[int, int, int]]:
    """Square tiles of ``side`` covering the image with half-tile overlap."""
    step = side // 2
    xs = list(range(0, max(w - side, 0) + 1, step)) or [0]
    ys = list(range(0, max(h - side, 0) + 1, step)) or [0]
    if xs[-1] + side < w:
        xs.append(w - side)
    if ys[-1] + side < h:
        ys.append(h - side)
    return [(x, y, side) for y in ys for x in xs]


def _tile_sides(w: int, h: int, min_face_px: int) -> list[int]:
    """Tile sides, coarse to fine. The full-range net finds faces down to ~1/10 of its window."""
    finest = int(min_face_px * 9)
    sides = []
    side = max(w, h) // 2
    while side > finest:
        sides.append(side)
        side //= 2
    if side * 2 > finest and max(w, h) > finest:
        sides.append(finest)
    return sides


def _across_rotations(per_rotation: dict[int, RawDetections], s: DetectSettings) -> list[tuple[RawDetections, int]]:
    """One detection per face: the rotation whose copy scores the face highest.

    BlazeFace also fires, with lower scores and wrong keypoints, on faces turned 90 or 180 degrees,
    so the best-scoring rotation is the right one (checked on the astronaut at 0-60 degrees).
    """
    pooled = []
    for k, cand in per_rotation.items():
        d = weighted_nms(cand, s.iou_threshold, s.score_threshold)
        pooled += [(RawDetections(d.boxes[i : i + 1], d.keypoints[i : i + 1], d.scores[i : i + 1]), k) for i in range(len(d.scores))]
    pooled.sort(key=lambda t: -float(t[0].scores[0]))
    kept: list[tuple[RawDetections, int]] = []
    for det, k in pooled:
        if all(iou(det.boxes[0], other.boxes)[0] <= s.iou_threshold for other, _ in kept):
            kept.append((det, k))
    return kept


def detect_faces(image: np.ndarray, settings: DetectSettings = DetectSettings(), root: Path | None = None) -> list[FaceBox]:
    """All faces in ``image`` (H, W, 3) uint8 RGB that FaceMesh confirms, largest first.

    Whole image first (short and full range, 4 rotations unless ``rotations`` is off), then finer
    upright tiles of the full-range net until a face is found (all scales with ``exhaustive``).
    """
    _check_image(image)
    s = settings
    root = ensure_models(["blazeface_short", "blazeface_full", "facemesh"], root)
    h, w = image.shape[:2]
    rotations = (0, 1, 2, 3) if s.rotations else (0,)
    whole = [(0, 0, max(w, h))]
    cands = [
        _run_detector(image, whole, "blazeface_short", SHORT_RANGE, root, s, rotations),
        _run_detector(image, whole, "blazeface_full", FULL_RANGE, root, s, rotations),
    ]
    checked: dict[tuple[float, ...], FaceBox | None] = {}

    def confirmed() -> list[FaceBox]:
        merged = {k: _concat([c[k] for c in cands]) for k in rotations}
        faces = []
        for d, k in _across_rotations(merged, s):
            key = tuple(np.round(d.boxes[0], 1))
            if key not in checked:
                box = FaceBox(d.boxes[0], d.keypoints[0], float(d.scores[0]), 90 * k, 0.0)
                _, presence = _facemesh(image, roi_from_detection(box.box, box.keypoints), root, s.threads)
                checked[key] = replace(box, presence=presence) if presence >= s.min_presence else None
            if checked[key] is not None:
                faces.append(checked[key])
        return faces

    found = confirmed()
    for side in _tile_sides(w, h, s.min_face_px):
        if found and not s.exhaustive:
            break
        # Tiles run upright only: 4 rotations would quadruple the cost (~7 s instead of ~2 s for a 12 MP
        # photo), for small faces that in practice stand upright.
        tiles = _run_detector(image, _tiles(w, h, side), "blazeface_full", FULL_RANGE, root, s, (0,))
        cands.append({k: tiles.get(k, _concat([])) for k in rotations})
        found = confirmed()
    return sorted(found, key=lambda f: -f.area)


# ---------------------------------------------------------------- landmarks


def _facemesh(image: np.ndarray, roi: Roi, root: Path, threads: int) -> tuple[np.ndarray, float]:
    sess = onnx_session(root / "facemesh.onnx", threads)
    x = crop(image, roi).astype(np.float32) / 255.0
    raw, flag = sess.run(None, {"image": np.ascontiguousarray(x.transpose(2, 0, 1)[None])})
    presence = float(1.0 / (1.0 + math.exp(-float(np.clip(flag.reshape(-1)[0], -80, 80)))))
    return landmarks_to_image(raw.reshape(-1), roi), presence


def face_landmarks(image: np.ndarray, face: FaceBox, settings: DetectSettings = DetectSettings(), root: Path | None = None) -> FaceLandmarks | None:
    """FaceMesh landmarks for one detected face, or None when FaceMesh says it is not a face."""
    _check_image(image)
    root = ensure_models(["facemesh"], root)
    roi = roi_from_detection(face.box, face.keypoints)
    points, presence = _facemesh(image, roi, root, settings.threads)
    for _ in range(settings.landmark_passes - 1):
        roi = roi_from_landmarks(points)
        points, presence = _facemesh(image, roi, root, settings.threads)
    if presence < settings.min_presence:
        return None
    return FaceLandmarks(points, points[IBUG68_FROM_FACEMESH, :2].copy(), presence, head_pose(points), roi)


def _check_image(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        got = f"{type(image).__name__} {getattr(image, 'shape', '')} {getattr(image, 'dtype', '')}"
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {got}")


def detect(image: np.ndarray, settings: DetectSettings = DetectSettings(), root: Path | None = None) -> Detection:
    """Faces, and landmarks + pose + identity of the largest face (of every face with all_faces)."""
    _check_image(image)
    t0 = time.perf_counter()
    boxes = detect_faces(image, settings, root)
    t1 = time.perf_counter()
    faces: list[Face] = []
    chosen = None
    for i, box in enumerate(boxes):
        if chosen is not None and not settings.all_faces:
            faces.append(Face(box))
            continue
        lm = face_landmarks(image, box, settings, root)
        ident = None
        if lm is not None and settings.identity:
            from .dlib_resnet import face_descriptor_onnx

            ident = face_descriptor_onnx(image, lm.ibug68, ensure_models(["dlib_resnet"], root), settings.threads)
        faces.append(Face(box, lm, ident))
        if lm is not None and chosen is None:
            chosen = i
    t2 = time.perf_counter()
    h, w = image.shape[:2]
    return Detection(w, h, tuple(faces), chosen, {"detect": t1 - t0, "landmarks": t2 - t1})
