"""dlib face-chip alignment: geometry, numpy extraction (bit-exact with dlib), differentiable torch version."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fitme_cli.perception import face_chip as fc
from fitme_cli.perception.face_chip import (
    extract_chip,
    extract_chip_torch,
    face_chip_affine,
    get_face_chip_details,
)

def _synthetic_landmarks(scale: float = 100.0, angle: float = 0.2, centre=(120.0, 110.0)) -> np.ndarray:
    """A face-like 68-point shape: dlib's mean face (plus a jaw), scaled, tilted and placed."""
    unit = np.zeros((68, 2))
    unit[17:] = np.stack([fc._MEAN_FACE_X, fc._MEAN_FACE_Y], 1)
    unit[:17] = np.stack([np.linspace(0, 1, 17), 0.5 + 0.4 * np.sin(np.linspace(0, np.pi, 17))], 1)  # a jaw
    c, s = np.cos(angle), np.sin(angle)
    return (unit - 0.5) @ np.array([[c, s], [-s, c]]) * scale + np.asarray(centre)


def _image(h: int = 240, w: int = 260, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    smooth = np.stack([128 + 100 * np.sin(xx / 13.0 + k) * np.cos(yy / 17.0 - k) for k in range(3)], -1)
    return np.clip(smooth + rng.normal(0, 8, smooth.shape), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# geometry


def test_affine_maps_template_points_to_their_chip_positions():
    lm = _synthetic_landmarks()
    a = face_chip_affine(lm, 150, 0.25)
    assert a.shape == (2, 3) and a.dtype == np.float64
    chip_pts = lm @ a[:, :2].T + a[:, 2]
    expected = (0.25 + np.stack([fc._MEAN_FACE_X, fc._MEAN_FACE_Y], 1)) / 1.5 * 150
    # An exact similarity fit, apart from dlib's (size*scale - 1)/(size - 1) sampling step.
    assert np.abs(chip_pts[27:48] - expected[10:31]).max() < 0.6


def test_details_round_trip():
    det = get_face_chip_details(_synthetic_landmarks(angle=-0.4), 150, 0.25)
    fwd, inv = det.image_to_chip(), det.chip_to_image()
    composed = fwd[:, :2] @ inv[:, :2]
    assert np.allclose(composed, np.eye(2)) and np.allclose(fwd[:, :2] @ inv[:, 2] + fwd[:, 2], 0)
    assert det.size == 150 and abs(det.angle - (-0.4)) < 1e-9


@pytest.mark.parametrize(
    "bad",
    [np.zeros((5, 2)), np.zeros((68, 3)), np.full((68, 2), np.nan), [[0, 0]] * 67],
)
def test_bad_landmarks(bad):
    with pytest.raises(ValueError):
        face_chip_affine(np.asarray(bad, dtype=float))


def test_bad_size_padding_and_image():
    lm = _synthetic_landmarks()
    with pytest.raises(ValueError, match="size"):
        face_chip_affine(lm, size=1)
    with pytest.raises(ValueError, match="padding"):
        face_chip_affine(lm, padding=-0.1)
    with pytest.raises(ValueError, match="uint8"):
        extract_chip(_image().astype(np.float32), lm)
    with pytest.raises(ValueError, match="uint8"):
        extract_chip(_image()[..., 0], lm)


def test_extract_chip_shapes_and_outside():
    img = _image()
    chip = extract_chip(img, _synthetic_landmarks(), size=64, padding=0.1)
    assert chip.shape == (64, 64, 3) and chip.dtype == np.uint8 and chip.std() > 0
    far = _synthetic_landmarks(centre=(5000.0, 5000.0))
    assert not extract_chip(img, far).any()
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float()
    a = torch.from_numpy(face_chip_affine(far))[None]
    assert not extract_chip_torch(x, a).any()


# ----------------------------------------------------------------------------------------------
# torch extraction


def _torch_chip(img: np.ndarray, lm: np.ndarray, size: int = 150, antialias: bool = True) -> np.ndarray:
    x = torch.from_numpy(img).permute(2, 0, 1)[None].double()
    a = torch.from_numpy(face_chip_affine(lm, size))[None]
    return extract_chip_torch(x, a, size, antialias)[0].permute(1, 2, 0).numpy()


@pytest.mark.parametrize("scale,steps", [(100.0, 0), (500.0, 2)])  # steps: dlib's pyramid levels
def test_torch_matches_numpy(scale, steps):
    img = _image(700, 700) if scale > 100 else _image()
    lm = _synthetic_landmarks(scale=scale, centre=(350.0, 340.0) if scale > 100 else (120.0, 110.0))
    ref = extract_chip(img, lm).astype(np.float64)
    diff = np.abs(_torch_chip(img, lm) - ref)
    # dlib truncates to integers once per pyramid level and once at the end: each costs < 1.
    assert diff.max() < steps + 1
    assert diff.mean() < 0.5 * (steps + 1) + 0.1


def test_torch_batch_matches_single_calls():
    img = _image(700, 700)
    lms = [_synthetic_landmarks(scale=500.0, centre=(350.0, 340.0)), _synthetic_landmarks(scale=90.0, angle=-0.3, centre=(300.0, 200.0))]
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float().repeat(2, 1, 1, 1)
    a = torch.from_numpy(np.stack([face_chip_affine(lm, 96) for lm in lms]))
    batch = extract_chip_torch(x, a, 96)
    assert batch.shape == (2, 3, 96, 96) and batch.dtype == torch.float32
    for i in range(2):
        assert torch.allclose(batch[i], extract_chip_torch(x[i : i + 1], a[i : i + 1], 96)[0])


def test_torch_bad_inputs():
    x = torch.rand(1, 3, 32, 32)
    a = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]]])
    with pytest.raises(ValueError, match="B, 3, H, W"):
        extract_chip_torch(x[0], a)
    with pytest.raises(ValueError, match="floating"):
        extract_chip_torch((x * 255).to(torch.uint8), a)
    with pytest.raises(ValueError, match="affine"):
        extract_chip_torch(x, a[0])
    with pytest.raises(ValueError, match="invertible"):
        extract_chip_torch(x, torch.zeros(1, 2, 3))
    with pytest.raises(ValueError, match="size"):
        extract_chip_torch(x, a, size=0)


def _small_case(antialias: bool) -> tuple[torch.Tensor, torch.Tensor, int]:
    gen = torch.Generator().manual_seed(0)
    size = 4
    img = torch.rand(1, 3, 16, 16, generator=gen, dtype=torch.float64)
    # chip -> image: a rotated square spanning 3 px (no pyramid) or 10 px (one pyramid step)
    span = 10.0 if antialias else 3.0
    c, s = np.cos(0.3), np.sin(0.3)
    step = span / (size - 1)
    lin = np.array([[c, -s], [s, c]]) * step
    centre = np.array([7.9, 8.3])
    inv = np.concatenate([lin, (centre - lin @ np.array([1.5, 1.5]))[:, None]], 1)
    fwd = np.linalg.inv(inv[:, :2])
    a = torch.from_numpy(np.concatenate([fwd, -(fwd @ inv[:, 2])[:, None]], 1))[None]
    return img, a, size


@pytest.mark.parametrize("antialias", [False, True])
def test_gradcheck_torch_chip(antialias):
    img, a, size = _small_case(antialias)
    inv = np.linalg.inv(np.vstack([a[0].numpy(), [0, 0, 1]]))[:2]
    assert fc._plan(inv, size, 16, 16)[0] == int(antialias)  # the pyramid path is exercised
    img.requires_grad_(True)
    a.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda i, m: extract_chip_torch(i, m, size, antialias), (img, a), eps=1e-6, atol=1e-5)


# ----------------------------------------------------------------------------------------------
# dlib reference


@pytest.fixture(scope="module")
def dlib_tools():
    dlib = pytest.importorskip("dlib")
    pytest.importorskip("skimage")
    from fitme_cli.perception.store import package_file

    sp = package_file("face-recognition-models", "face_recognition_models",
                      "models/shape_predictor_68_face_landmarks.dat", "CC0-1.0").path
    return dlib, dlib.shape_predictor(str(sp)), dlib.get_frontal_face_detector()


def _faces(dlib, detector):
    """Real photos with a face box: the astronaut (detected) and the cameraman (profile, fixed box)."""
    import cv2
    from skimage import data

    astro = data.astronaut()
    box = max(detector(astro, 1), key=lambda r: r.area())
    camera = np.repeat(data.camera()[..., None], 3, 2)
    rot = cv2.warpAffine(astro, cv2.getRotationMatrix2D((256, 256), 25, 1.0), (512, 512))
    big = cv2.resize(astro, None, fx=3.3, fy=3.3, interpolation=cv2.INTER_CUBIC)  # pyramid path
    return [
        ("astronaut", astro, box),
        ("cameraman", camera, dlib.rectangle(175, 95, 265, 195)),
        ("astronaut rotated", rot, max(detector(rot, 1), key=lambda r: r.area())),
        ("astronaut x3.3", big, dlib.rectangle(*(int(v * 3.3) for v in (box.left(), box.top(), box.right(), box.bottom())))),
        ("astronaut at the border", np.ascontiguousarray(astro[90:, 185:]), dlib.rectangle(box.left() - 185, box.top() - 90, box.right() - 185, box.bottom() - 90)),
    ]


def test_chips_match_dlib_bit_for_bit(dlib_tools):
    dlib, predictor, detector = dlib_tools
    for name, img, box in _faces(dlib, detector):
        shape = predictor(img, box)
        lm = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)
        ref_det = dlib.get_face_chip_details(shape, 150, 0.25)
        det = get_face_chip_details(lm, 150, 0.25)
        r = ref_det.rect
        assert np.allclose(det.rect, (r.left(), r.top(), r.right(), r.bottom()), atol=1e-9), name
        assert abs(det.angle - ref_det.angle) < 1e-12, name
        ref = dlib.get_face_chip(img, shape, 150, 0.25)
        ours = extract_chip(img, lm, 150, 0.25)
        assert np.array_equal(ours, ref), f"{name}: max diff {np.abs(ours.astype(int) - ref).max()}"
        diff = np.abs(_torch_chip(img, lm) - ref)
        assert diff.max() <= 2.0 and diff.mean() < 1.0, name
