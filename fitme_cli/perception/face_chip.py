"""dlib's face-chip alignment (``get_face_chip_details`` + ``extract_image_chip``), in numpy and torch.

dlib's face descriptor was trained on chips cut this way, so matching it matters more than elegance:

* The chip geometry is a least-squares similarity (Umeyama) from a mean-face template to 33 of the
  68 iBUG landmarks (eyebrows and lower lip left out), turned into a rectangle + angle. The first and
  last chip pixel centres land on that rectangle's edges, so the sampling step is
  ``(size*scale - 1) / (size - 1)``, not the similarity's ``scale``.
* When the chip is much smaller than the face, dlib first shrinks the image with its 2:1 Gaussian
  pyramid (5-tap [1 4 6 4 1], integer arithmetic, valid borders) and maps coordinates with its
  ``point_down`` convention ``p/2 - (1.25, 0.75)``; ``extract_chip`` reproduces that bit for bit,
  ``extract_chip_torch`` in float and differentiably.
* Bilinear samples whose 2x2 neighbourhood leaves the image are black; values are truncated to uint8.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "ChipDetails",
    "get_face_chip_details",
    "face_chip_affine",
    "extract_chip",
    "extract_chip_torch",
]

# dlib's mean face (interpolation.h), iBUG points 17..67 in a unit square. Data, Boost Software License.
_MEAN_FACE_X = np.array([
    0.000213256, 0.0752622, 0.18113, 0.29077, 0.393397, 0.586856, 0.689483, 0.799124,
    0.904991, 0.98004, 0.490127, 0.490127, 0.490127, 0.490127, 0.36688, 0.426036,
    0.490127, 0.554217, 0.613373, 0.121737, 0.187122, 0.265825, 0.334606, 0.260918,
    0.182743, 0.645647, 0.714428, 0.793132, 0.858516, 0.79751, 0.719335, 0.254149,
    0.340985, 0.428858, 0.490127, 0.551395, 0.639268, 0.726104, 0.642159, 0.556721,
    0.490127, 0.423532, 0.338094, 0.290379, 0.428096, 0.490127, 0.552157, 0.689874,
    0.553364, 0.490127, 0.42689,
])
_MEAN_FACE_Y = np.array([
    0.106454, 0.038915, 0.0187482, 0.0344891, 0.0773906, 0.0773906, 0.0344891,
    0.0187482, 0.038915, 0.106454, 0.203352, 0.307009, 0.409805, 0.515625, 0.587326,
    0.609345, 0.628106, 0.609345, 0.587326, 0.216423, 0.178758, 0.179852, 0.231733,
    0.245099, 0.244077, 0.231733, 0.179852, 0.178758, 0.216423, 0.244077, 0.245099,
    0.780233, 0.745405, 0.727388, 0.742578, 0.727388, 0.745405, 0.780233, 0.864805,
    0.902192, 0.909281, 0.902192, 0.864805, 0.784792, 0.778746, 0.785343, 0.778746,
    0.784792, 0.824182, 0.831803, 0.824182,
])
# Landmarks used for the fit: 27..54 and 60..64 (no eyebrows 17..26, no lower lip 55..59 / 65..67).
_FIT_POINTS = np.array([i for i in range(27, 68) if not (55 <= i <= 59 or 65 <= i <= 67)])
_PYR_OFFSET = np.array([1.25, 0.75])  # dlib pyramid_down<2>::point_down(p) = p/2 - offset
_PYR_TAPS = np.array([1, 4, 6, 4, 1], dtype=np.int64)


@dataclass(frozen=True)
class ChipDetails:
    """dlib's ``chip_details``: a rotated rectangle in image pixels and the chip's size.

    ``rect`` is dlib's drectangle (left, top, right, bottom) before rotation by ``angle`` (radians)
    about its centre; chip pixel (0, 0) lands on its rotated top-left corner, (size-1, size-1) on
    the bottom-right one.
    """

    rect: tuple[float, float, float, float]
    angle: float
    size: int

    def chip_to_image(self) -> np.ndarray:
        """(2, 3) float64 affine mapping chip pixel (x, y) to image pixel (x, y)."""
        return _rect_map(np.asarray(self.rect, dtype=np.float64), self.angle, self.size)

    def image_to_chip(self) -> np.ndarray:
        """(2, 3) float64 affine mapping image pixel (x, y) to chip pixel (x, y)."""
        return _invert_affine(self.chip_to_image())


def _check_landmarks(landmarks68: np.ndarray) -> np.ndarray:
    pts = np.asarray(landmarks68, dtype=np.float64)
    if pts.shape != (68, 2):
        raise ValueError(f"expected 68 iBUG landmarks as a (68, 2) array of (x, y) pixels, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("landmarks contain NaN or infinity")
    return pts


def _check_size_padding(size: int, padding: float) -> None:
    if int(size) != size or size < 2:
        raise ValueError(f"chip size must be an integer >= 2, got {size!r}")
    if not padding >= 0:  # also rejects NaN
        raise ValueError(f"padding must be >= 0, got {padding!r}")


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares similarity dst ~ M @ src + t (Umeyama 1991), as dlib's find_similarity_transform."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    s, d = src - mu_s, dst - mu_d
    var_s = (s**2).sum(1).mean()
    cov = d.T @ s / len(src)
    u, sv, vt = np.linalg.svd(cov)
    sign = np.eye(2)
    if np.linalg.det(cov) < 0 or (np.linalg.det(cov) == 0 and np.linalg.det(u) * np.linalg.det(vt) < 0):
        sign[1, 1] = -1
    rot = u @ sign @ vt
    c = np.trace(np.diag(sv) @ sign) / var_s if var_s > 0 else 1.0
    m = c * rot
    return m, mu_d - m @ mu_s


def get_face_chip_details(landmarks68: np.ndarray, size: int = 150, padding: float = 0.25) -> ChipDetails:
    """dlib's ``get_face_chip_details`` for a 68-point iBUG shape, (68, 2) float (x, y) image pixels."""
    pts = _check_landmarks(landmarks68)
    _check_size_padding(size, padding)
    template = np.stack([_MEAN_FACE_X, _MEAN_FACE_Y], 1)[_FIT_POINTS - 17]
    chip_pts = (padding + template) / (2 * padding + 1) * size
    m, t = _similarity(chip_pts, pts[_FIT_POINTS])
    angle = math.atan2(m[1, 0], m[0, 0])
    scale = math.hypot(m[0, 0], m[1, 0])
    if not size * scale > 1:
        raise ValueError("landmarks are degenerate (the face would be smaller than a chip pixel)")
    cx, cy = m @ np.array([size / 2.0, size / 2.0]) + t
    half = (size * scale - 1) / 2  # dlib's centered_drect(p, w, h) spans w-1 between edges
    return ChipDetails((cx - half, cy - half, cx + half, cy + half), angle, int(size))


def face_chip_affine(landmarks68: np.ndarray, size: int = 150, padding: float = 0.25) -> np.ndarray:
    """(2, 3) float64 affine mapping image pixels to dlib's face-chip pixels for 68 iBUG landmarks."""
    return get_face_chip_details(landmarks68, size, padding).image_to_chip()


# ----------------------------------------------------------------------------------------------
# geometry helpers


def _rect_map(rect: np.ndarray, angle: float, size: int) -> np.ndarray:
    """Chip pixel -> rect coordinates, as dlib's three-corner find_affine_transform builds it."""
    left, top, right, bottom = rect
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    lin = rot @ np.diag([(right - left) / (size - 1), (bottom - top) / (size - 1)])
    centre = np.array([(left + right) / 2, (top + bottom) / 2])
    offset = centre - lin @ np.array([(size - 1) / 2, (size - 1) / 2])
    return np.concatenate([lin, offset[:, None]], 1)


def _invert_affine(a: np.ndarray) -> np.ndarray:
    lin = np.linalg.inv(a[:, :2])
    return np.concatenate([lin, -(lin @ a[:, 2])[:, None]], 1)


def _rect_down(rect: np.ndarray) -> np.ndarray:
    return np.concatenate([rect[:2] / 2 - _PYR_OFFSET, rect[2:] / 2 - _PYR_OFFSET])


def _area(rect: np.ndarray) -> float:
    """dlib drectangle area: width = right - left + 1."""
    w, h = rect[2] - rect[0] + 1, rect[3] - rect[1] + 1
    return 0.0 if w < 1 or h < 1 else float(w * h)


def _round(v: float) -> int:
    return int(math.floor(v + 0.5))


# ----------------------------------------------------------------------------------------------
# numpy extraction (bit-exact with dlib)


def _pyramid_down(img: np.ndarray) -> np.ndarray:
    """dlib pyramid_down<2> on an (H, W, 3) uint8 image: separable [1 4 6 4 1], valid, integer /256."""
    h, w = img.shape[:2]
    if h <= 8 or w <= 8:
        return np.zeros((0, 0, 3), np.uint8)
    ow, oh = (w - 3) // 2, (h - 3) // 2
    x = img.astype(np.int64)
    rows = sum(t * x[:, k : k + 2 * ow : 2] for k, t in enumerate(_PYR_TAPS))
    out = sum(t * rows[k : k + 2 * oh : 2] for k, t in enumerate(_PYR_TAPS))
    return (out // 256).astype(np.uint8)


def _bilinear_uint8(src: np.ndarray, affine: np.ndarray, size: int) -> np.ndarray:
    """Sample ``src`` at ``affine @ (x, y, 1)`` per chip pixel; black where the 2x2 support leaves it."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x = affine[0, 0] * u + affine[0, 1] * v + affine[0, 2]
    y = affine[1, 0] * u + affine[1, 1] * v + affine[1, 2]
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    h, w = src.shape[:2]
    if h < 2 or w < 2:  # dlib's pyramid gives up on crops of 8 px or less
        return np.zeros((size, size, 3), np.uint8)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.where(ok, x0, 0), np.where(ok, y0, 0)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    s = src.astype(np.float64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    val = (1 - fy) * ((1 - fx) * s[y0, x0] + fx * s[y0, x1]) + fy * ((1 - fx) * s[y1, x0] + fx * s[y1, x1])
    out = np.clip(val, 0, 255).astype(np.uint8)  # dlib's assign_pixel truncates
    out[~ok] = 0
    return out


def _check_image_uint8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an RGB image as uint8 (H, W, 3), got {img.dtype} {img.shape}")
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise ValueError(f"image too small: {img.shape[:2]}")
    return img


def extract_chip(image_rgb: np.ndarray, landmarks68: np.ndarray, size: int = 150, padding: float = 0.25) -> np.ndarray:
    """dlib's aligned face chip: ``dlib.get_face_chip(img, shape, size, padding)``, bit for bit.

    ``image_rgb`` is uint8 (H, W, 3); ``landmarks68`` (68, 2) (x, y) pixels. Returns uint8 (size, size, 3).
    """
    img = _check_image_uint8(image_rgb)
    det = get_face_chip_details(landmarks68, size, padding)
    return _extract(img, det)


def _plan(chip_to_image: np.ndarray, size: int, h: int, w: int) -> tuple[int, tuple[int, int, int, int] | None]:
    """dlib's extraction plan: pyramid steps, and the crop (left, top, right, bottom, inclusive) the
    pyramid is built on; None when the chip misses the image."""
    lin, centre = chip_to_image[:, :2], chip_to_image @ np.array([(size - 1) / 2, (size - 1) / 2, 1.0])
    half = np.linalg.norm(lin, axis=0) * (size - 1) / 2  # dlib's drectangle, before rotation
    rect = np.concatenate([centre - half, centre + half])
    steps, grow, r = 0, 2.0, _rect_down(rect)
    while _area(r) > size * size:
        r, steps, grow = _rect_down(r), steps + 1, grow * 2 + 2
    corners = chip_to_image @ np.array([[0, size - 1, 0, size - 1], [0, 0, size - 1, size - 1], [1, 1, 1, 1.0]])
    lo = np.maximum(corners.min(1) - grow, 0.0)
    hi = np.minimum(corners.max(1) + grow, [w - 1.0, h - 1.0])
    box = tuple(_round(v) for v in (lo[0], lo[1], hi[0], hi[1]))
    return steps, (box if box[2] >= box[0] and box[3] >= box[1] else None)


def _level_map(chip_to_image: np.ndarray, box: tuple[int, int, int, int], steps: int) -> np.ndarray:
    """Chip px -> pixels of the crop's pyramid level ``steps``, with dlib's point_down convention."""
    m = chip_to_image.copy()
    m[:, 2] -= box[:2]
    for _ in range(steps):
        m = m / 2
        m[:, 2] -= _PYR_OFFSET
    return m


def _extract(img: np.ndarray, det: ChipDetails) -> np.ndarray:
    size, chip_to_image = det.size, det.chip_to_image()
    steps, box = _plan(chip_to_image, size, *img.shape[:2])
    if box is None:
        return np.zeros((size, size, 3), np.uint8)
    src = img[box[1] : box[3] + 1, box[0] : box[2] + 1]
    for _ in range(steps):
        src = _pyramid_down(src)
    return _bilinear_uint8(src, _level_map(chip_to_image, box, steps), size)


# ----------------------------------------------------------------------------------------------
# torch extraction (differentiable)


def _pyramid_kernel(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    k1 = torch.tensor(_PYR_TAPS.tolist(), dtype=dtype, device=device)
    return (torch.outer(k1, k1) / 256).expand(3, 1, 5, 5).contiguous()


def _sample(src: torch.Tensor, m: torch.Tensor, size: int) -> torch.Tensor:
    """Bilinear samples of src (3, H, W) at m @ (x, y, 1) per chip pixel, black like dlib where the
    2x2 support leaves the image."""
    u = torch.arange(size, dtype=src.dtype, device=src.device)
    x = m[0, 0] * u[None, :] + m[0, 1] * u[:, None] + m[0, 2]
    y = m[1, 0] * u[None, :] + m[1, 1] * u[:, None] + m[1, 2]
    h, w = src.shape[-2:]
    grid = torch.stack([2 * x / max(w - 1, 1) - 1, 2 * y / max(h - 1, 1) - 1], -1)[None]
    out = F.grid_sample(src[None], grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0]
    inside = ((x >= 0) & (x < w - 1) & (y >= 0) & (y < h - 1)).detach()
    return out * inside.to(out.dtype)


def extract_chip_torch(image: torch.Tensor, affine: torch.Tensor, size: int = 150, antialias: bool = True) -> torch.Tensor:
    """Differentiable face chip: image (B, 3, H, W) float, affine (B, 2, 3) image px -> chip px
    (e.g. ``face_chip_affine``). Returns (B, 3, size, size) in the image's dtype and value range.

    Follows ``extract_chip``: same crop and, with ``antialias``, the same 2:1 Gaussian pyramid steps
    for large faces, in float (no uint8 truncation). Gradients reach ``image`` and ``affine``.
    """
    if not isinstance(image, torch.Tensor) or image.ndim != 4 or image.shape[1] != 3:
        raise ValueError(f"expected image as a (B, 3, H, W) tensor, got {getattr(image, 'shape', type(image))}")
    if not image.is_floating_point():
        raise ValueError(f"expected a floating-point image, got {image.dtype}")
    if not isinstance(affine, torch.Tensor) or tuple(affine.shape) != (image.shape[0], 2, 3):
        raise ValueError(f"expected affine as a ({image.shape[0]}, 2, 3) tensor, got {getattr(affine, 'shape', type(affine))}")
    if int(size) != size or size < 2:
        raise ValueError(f"chip size must be an integer >= 2, got {size!r}")
    affine = affine.to(image.dtype)
    if not bool(torch.isfinite(affine).all()) or bool((torch.linalg.det(affine[:, :, :2].detach()) == 0).any()):
        raise ValueError("affine must be finite and invertible")
    inv_lin = torch.linalg.inv(affine[:, :, :2])
    inv = torch.cat([inv_lin, -(inv_lin @ affine[:, :, 2:])], 2)  # chip px -> image px
    h, w = image.shape[-2:]
    chips = []
    for b in range(image.shape[0]):
        steps, box = _plan(inv[b].detach().cpu().double().numpy(), size, h, w)
        steps = steps if antialias else 0
        src = image[b] if box is None else image[b, :, box[1] : box[3] + 1, box[0] : box[2] + 1]
        for _ in range(steps):
            if min(src.shape[-2:]) <= 8:  # dlib's pyramid gives up: a black chip, like extract_chip
                box = None
                break
            src = F.conv2d(src[None], _pyramid_kernel(image.dtype, image.device), stride=2, groups=3)[0]
        if box is None:  # the chip misses the image: black (times the image, to stay in the graph)
            chips.append(image[b, :, :1, :1].expand(3, size, size) * 0)
            continue
        # the same map as _level_map, kept in torch so gradients reach the affine
        m = inv[b].clone()
        m = torch.cat([m[:, :2], m[:, 2:] - torch.tensor([[box[0]], [box[1]]], dtype=m.dtype, device=m.device)], 1)
        offset = torch.as_tensor(_PYR_OFFSET, dtype=m.dtype, device=m.device)[:, None]
        for _ in range(steps):
            m = m / 2
            m = torch.cat([m[:, :2], m[:, 2:] - offset], 1)
        chips.append(_sample(src, m, size))
    return torch.stack(chips)
