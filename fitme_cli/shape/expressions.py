"""ARKit-named expression blendshapes, built procedurally on the mean head.

Each blendshape is a localized displacement field (mm at full activation): a smooth weight (Gaussian
falloff from FaceMesh landmark groups, or a soft jaw/lip split) times a motion (a jaw rotation about a
pivot in front of the ears, lid closure to the opposite lid, corner pulls, ...). Left/Right are the
subject's, i.e. model +x is Left. With eye holes and no mouth interior, the eye-look shapes and
tongueOut are zero fields (kept so that all 52 ARKit names exist for export); their prior scale is tiny.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FaceParts", "face_parts", "build_expressions", "EXPRESSION_PRIOR_SCALE"]

# Prior standard deviation of each activation (L_e divides by it): shapes that photos show often get 0.5.
EXPRESSION_PRIOR_SCALE = 0.5
_NO_GEOMETRY_SCALE = 1e-3


@dataclass(frozen=True)
class FaceParts:
    """Landmark index groups (vertex ids < 468), split by side using the mean (x > 0 is the subject's left)."""

    eye_upper: dict[str, np.ndarray]
    eye_lower: dict[str, np.ndarray]
    brow: dict[str, np.ndarray]
    lip_upper_inner: np.ndarray
    lip_lower_inner: np.ndarray
    lips: np.ndarray
    corner: dict[str, int]
    cheek: dict[str, int]
    nose_side: dict[str, int]


def face_parts(mean: np.ndarray, contours: dict[str, np.ndarray]) -> FaceParts:
    def ids(name: str) -> np.ndarray:
        return np.unique(contours[name])

    eye_up, eye_lo, brow = {}, {}, {}
    for side, key in (("Left", "left"), ("Right", "right")):
        e = ids(f"{key}_eye")
        if np.sign(mean[e, 0].mean()) != (1 if side == "Left" else -1):  # MediaPipe names are the subject's
            key = "right" if key == "left" else "left"
            e = ids(f"{key}_eye")
        corners = e[[np.argmin(mean[e, 0]), np.argmax(mean[e, 0])]]
        a, b = mean[corners[0]], mean[corners[1]]
        t = (mean[e, 0] - a[0]) / (b[0] - a[0])
        line_y = a[1] + t * (b[1] - a[1])
        rest = ~np.isin(e, corners)
        eye_up[side] = e[rest & (mean[e, 1] > line_y)]
        eye_lo[side] = e[rest & (mean[e, 1] <= line_y)]
        brow[side] = ids(f"{key}_eyebrow")
    lips = ids("lips")
    corner = {"Left": 291 if mean[291, 0] > 0 else 61, "Right": 61 if mean[291, 0] > 0 else 291}
    upper_inner = np.array([191, 80, 81, 82, 13, 312, 311, 310, 415])
    lower_inner = np.array([95, 88, 178, 87, 14, 317, 402, 318, 324])
    side = lambda l, r: {"Left": l, "Right": r} if mean[l, 0] > 0 else {"Left": r, "Right": l}  # noqa: E731
    return FaceParts(eye_up, eye_lo, brow, upper_inner, lower_inner, lips, corner, side(425, 205), side(358, 129))


def _falloff(v: np.ndarray, anchors: np.ndarray, radius: float) -> np.ndarray:
    d2 = ((v[:, None, :] - anchors[None, :, :]) ** 2).sum(-1).min(1)
    return np.exp(-d2 / (2 * radius**2))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -60, 60)))


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def _mouth_chains(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mouth hole's boundary split at the inner corners (78, 308): (upper chain, lower chain) vertex ids."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    key, count = np.unique(np.sort(e, 1), axis=0, return_counts=True)
    adj: dict[int, list[int]] = {}
    for a, b in key[count == 1].tolist():
        adj.setdefault(a, []).append(b)
        adj.setdefault(b, []).append(a)
    chains = []
    for start in adj[78]:  # walk from one inner corner to the other, both ways round
        path, prev = [78, start], 78
        while path[-1] != 308:
            nxt = next(n for n in adj[path[-1]] if n != prev)
            prev = path[-1]
            path.append(nxt)
        chains.append(np.asarray(path))
    upper = next(c for c in chains if 13 in c)
    lower = next(c for c in chains if 14 in c)
    return upper, lower


def build_expressions(mean: np.ndarray, triangles: np.ndarray, parts: FaceParts,
                      names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3, E) displacement fields in mm at full activation, and (E,) prior scales, in ``names`` order."""
    v = mean
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    P = parts
    # the lip slit as a function of x, between the upper and lower inner lips
    mid = 0.5 * (v[P.lip_upper_inner] + v[P.lip_lower_inner])
    order = np.argsort(mid[:, 0])
    slit_y = np.interp(x, mid[order, 0], mid[order, 1])
    ear_z = v[[234, 454], 2].mean()
    pivot = np.array([0.0, v[[234, 454], 1].mean() - 5.0, ear_z - 15.0])
    front = _smoothstep((z - (ear_z - 30.0)) / 25.0)  # exactly zero from 30 mm behind the ear line
    # The jaw/lip split: nearer the lower lip than the upper one. Sharp at the lips (no zig-zag along the
    # slit: every lip vertex goes with its own lip) and widening away from them, so cheeks stretch
    # instead of creasing.
    upper_chain, lower_chain = _mouth_chains(triangles)
    upper_set = v[np.concatenate([upper_chain[1:-1], [185, 40, 39, 37, 0, 267, 269, 270, 409]])]
    lower_set = v[np.concatenate([lower_chain[1:-1], [146, 91, 181, 84, 17, 314, 405, 321, 375]])]
    dist = lambda a: np.sqrt(((v[:, None, :] - a[None]) ** 2).sum(-1).min(1))  # noqa: E731
    d_up, d_lo = dist(upper_set), dist(lower_set)
    d_lips = np.minimum(d_up, d_lo)
    lower = _sigmoid((d_up - d_lo) / (0.7 + 0.45 * d_lips)) * front * _sigmoid((80.0 - np.abs(x)) / 6.0)
    below_nose = _sigmoid((v[2, 1] - y) / 6.0)
    jaw_weight = lower * below_nose  # the lower face
    lips_w = _falloff(v, v[P.lips], 7.0) * front
    upper_lip_w = lips_w * (1 - lower / np.maximum(front, 1e-9)).clip(0, 1)
    lower_lip_w = lips_w * (lower / np.maximum(front, 1e-9)).clip(0, 1)
    fields: dict[str, np.ndarray] = {}

    def jaw_rotation(deg: float) -> np.ndarray:
        return ((v - pivot) @ _rot_x(deg).T + pivot) - v

    fields["jawOpen"] = jaw_weight[:, None] * jaw_rotation(15.0)  # ~26 mm at the lower lip
    fields["jawForward"] = jaw_weight[:, None] * np.array([0.0, 0.0, 6.0])
    for s, sign in (("Left", 1.0), ("Right", -1.0)):
        fields[f"jaw{s}"] = jaw_weight[:, None] * np.array([sign * 7.0, 0.0, 0.0])
    gap = np.maximum(v[P.lip_upper_inner, 1].mean() - v[P.lip_lower_inner, 1].mean(), 0.0)
    fields["mouthClose"] = (lower_lip_w[:, None] * [0, 0.5 * gap + 1.0, 0] - upper_lip_w[:, None] * [0, 0.5 * gap + 1.0, 0])
    centre = v[P.lips].mean(0)
    fields["mouthPucker"] = lips_w[:, None] * (np.stack([-(x - centre[0]) * 0.25, np.zeros_like(x), np.full_like(x, 6.0)], 1))
    fields["mouthFunnel"] = lips_w[:, None] * np.stack([-(x - centre[0]) * 0.15, np.sign(y - slit_y) * 3.0, np.full_like(x, 5.0)], 1)
    fields["mouthRollLower"] = lower_lip_w[:, None] * np.array([0.0, 1.5, -3.5])
    fields["mouthRollUpper"] = upper_lip_w[:, None] * np.array([0.0, -1.5, -3.5])
    fields["mouthShrugLower"] = (lower_lip_w * below_nose)[:, None] * np.array([0.0, 3.0, 1.0])
    fields["mouthShrugUpper"] = upper_lip_w[:, None] * np.array([0.0, 2.0, 1.0])
    mouth_region = _falloff(v, v[P.lips], 12.0) * front
    for s, sign in (("Left", 1.0), ("Right", -1.0)):
        c = v[P.corner[s]][None]
        cw = _falloff(v, c, 11.0) * front
        fields[f"mouth{s}"] = mouth_region[:, None] * np.array([sign * 6.0, 0.0, 0.0])
        fields[f"mouthSmile{s}"] = cw[:, None] * np.array([sign * 3.0, 6.0, -2.5])
        fields[f"mouthFrown{s}"] = cw[:, None] * np.array([0.0, -5.0, 0.0])
        fields[f"mouthStretch{s}"] = cw[:, None] * np.array([sign * 5.0, -2.0, -1.0])
        fields[f"mouthDimple{s}"] = cw[:, None] * np.array([sign * 2.0, 0.0, -3.0])
        fields[f"mouthPress{s}"] = (cw * lips_w)[:, None] * np.array([0.0, 0.0, -2.0]) + (cw * lower_lip_w)[:, None] * [0, 1.0, 0]
        half = _sigmoid(sign * x / 3.0)
        fields[f"mouthUpperUp{s}"] = (upper_lip_w * half)[:, None] * np.array([0.0, 4.0, 0.5])
        fields[f"mouthLowerDown{s}"] = (lower_lip_w * half)[:, None] * np.array([0.0, -4.0, 0.5])
        # eyes
        up, lo = P.eye_upper[s], P.eye_lower[s]
        lid_gap = np.interp(x, *_sorted_xy(v[up])) - np.interp(x, *_sorted_xy(v[lo]))
        ecx = v[np.concatenate([up, lo]), 0]
        in_eye_x = _sigmoid((ecx.max() + 2 - x) / 1.5) * _sigmoid((x - ecx.min() + 2) / 1.5)
        above = _sigmoid((y - np.interp(x, *_sorted_xy(v[lo]))) / 1.0)
        up_w = _falloff(v, v[up], 4.0) * in_eye_x * above
        lo_w = _falloff(v, v[lo], 4.0) * in_eye_x * (1 - above)
        fields[f"eyeBlink{s}"] = (up_w * np.maximum(lid_gap, 0))[:, None] * np.array([0.0, -1.0, 0.0])
        fields[f"eyeWide{s}"] = up_w[:, None] * np.array([0.0, 2.5, 0.0])
        fields[f"eyeSquint{s}"] = lo_w[:, None] * np.array([0.0, 2.0, 0.0]) + (up_w * 0.3)[:, None] * [0, -1.0, 0]
        for look in ("Up", "Down", "In", "Out"):
            fields[f"eyeLook{look}{s}"] = np.zeros_like(v)
        # brows and cheeks
        b = v[P.brow[s]]
        bw = _falloff(v, b, 9.0) * front
        inner = b[np.argsort(np.abs(b[:, 0]))[:3]]
        outer = b[np.argsort(-np.abs(b[:, 0]))[:3]]
        fields[f"browDown{s}"] = bw[:, None] * np.array([-sign * 2.0, -5.0, 0.0])
        fields[f"browOuterUp{s}"] = (_falloff(v, outer, 10.0) * front)[:, None] * np.array([0.0, 6.0, 0.0])
        cheek = v[P.cheek[s]][None]
        fields[f"cheekSquint{s}"] = (_falloff(v, cheek, 12.0) * front)[:, None] * np.array([0.0, 3.0, 1.0])
        fields[f"noseSneer{s}"] = (_falloff(v, v[P.nose_side[s]][None], 6.0) * front)[:, None] * np.array([0.0, 3.0, 0.5])
        if s == "Left":
            inner_left = inner
    inner_both = np.concatenate([inner_left, inner_left * [-1.0, 1.0, 1.0]])
    fields["browInnerUp"] = (_falloff(v, inner_both, 10.0) * front)[:, None] * np.array([0.0, 6.0, 0.0])
    cheeks = np.stack([v[P.cheek["Left"]], v[P.cheek["Right"]]])
    normal_out = np.stack([np.sign(x), np.zeros_like(x), np.full_like(x, 0.3)], 1)
    fields["cheekPuff"] = (_falloff(v, cheeks, 16.0) * front)[:, None] * normal_out * 5.0
    fields["tongueOut"] = np.zeros_like(v)
    missing = [n for n in names if n not in fields]
    if missing:
        raise ValueError(f"no recipe for blendshapes {missing}")
    basis = np.stack([fields[n] for n in names], axis=2)
    scale = np.array([_NO_GEOMETRY_SCALE if not fields[n].any() else EXPRESSION_PRIOR_SCALE for n in names])
    return basis, scale


def _sorted_xy(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.argsort(p[:, 0])
    return p[o, 0], p[o, 1]
