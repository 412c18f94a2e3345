"""dlib ResNet face descriptor: parser, torch module, ONNX export, and dlib itself as the reference."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fitme_cli.errors import ModelBuildError, ModelMissing
from fitme_cli.perception import dlib_resnet as dr
from fitme_cli.perception import face_chip as fc
from fitme_cli.perception.face_chip import extract_chip, extract_chip_torch, face_chip_affine
from fitme_cli.perception.onnx_runner import onnx_session
from fitme_cli.perception.store import sha256_file


@pytest.fixture(scope="session")
def built(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("models")
    return out, dr.build(out)


@pytest.fixture(scope="session")
def model(built) -> dr.DlibFaceDescriptor:
    return dr.load_dlib_resnet(built[0])


def _chip_tensor(chip: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(chip).permute(2, 0, 1)[None].float() / 255.0


# ----------------------------------------------------------------------------------------------
# parser


def test_parser_names_and_shapes():
    w = dr.read_dlib_resnet(dr.source_file().path)
    convs = [k for k in w if k.endswith(".weight") and "conv" in k]
    affines = [k for k in w if k.endswith(".gamma")]
    assert len(convs) == 29 and len(affines) == 29
    assert w["stem.conv.weight"].shape == (32, 3, 7, 7)
    assert w["blocks.3.conv1.weight"].shape == (64, 32, 3, 3)
    assert w["blocks.13.conv2.weight"].shape == (256, 256, 3, 3)
    assert w["fc.weight"].shape == (128, 256)
    assert np.allclose(w["input.mean"], [122.782, 117.001, 104.298], atol=1e-4)
    assert all(v.dtype == np.float32 and np.isfinite(v).all() for v in w.values())


def test_parser_rejects_bad_files(tmp_path):
    data = dr.source_file().path.read_bytes()
    for name, blob in [("truncated", data[: len(data) // 2]), ("garbage", b"\x01\x05hello" + bytes(100)),
                       ("trailing", data + b"\x00")]:
        f = tmp_path / f"{name}.dat"
        f.write_bytes(blob)
        with pytest.raises(ModelBuildError):
            dr.read_dlib_resnet(f)


# ----------------------------------------------------------------------------------------------
# build and module


def test_build_writes_files_and_card(built):
    out, card = built
    for ext in ("onnx", "json", "safetensors"):
        assert (out / f"dlib_resnet.{ext}").is_file()
    assert json.loads((out / "dlib_resnet.json").read_text()) == card
    assert card["source"]["sha256"] == sha256_file(dr.source_file().path)
    assert card["source"]["licence"] == "CC0-1.0" == card["licence"]
    assert card["input"]["name"] == "image" and card["input"]["shape"] == ["B", 3, 150, 150]
    assert card["checks"]["max_abs_torch_minus_onnx"] < 1e-4


def test_build_is_repeatable(tmp_path, built):
    card = dr.build(tmp_path)
    assert (tmp_path / "dlib_resnet.safetensors").read_bytes() == (built[0] / "dlib_resnet.safetensors").read_bytes()
    assert card["checks"]["max_abs_torch_minus_onnx"] < 1e-4
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left


def test_load_missing(tmp_path):
    with pytest.raises(ModelMissing):
        dr.load_dlib_resnet(tmp_path)


def test_forward_and_features_shapes(model):
    x = torch.rand(2, 3, 150, 150)
    with torch.no_grad():
        d = model(x)
        f = model.features(x)
    assert d.shape == (2, 128) and d.dtype == torch.float32
    assert torch.equal(f.descriptor, d)
    shapes = [tuple(a.shape[1:]) for a in f.activations]
    assert shapes == [(32, 35, 35), (32, 35, 35), (64, 17, 17), (128, 8, 8), (256, 4, 4), (256, 2, 2)]
    assert not any(p.requires_grad for p in model.buffers())


@pytest.mark.parametrize(
    "bad,match",
    [
        (np.zeros((1, 3, 150, 150), np.float32), "torch.Tensor"),
        (torch.zeros(1, 3, 150, 150, dtype=torch.uint8), "floating-point"),
        (torch.zeros(3, 150, 150), "shape"),
        (torch.zeros(1, 3, 112, 112), "shape"),
        (torch.zeros(1, 150, 150, 3), "shape"),
        (torch.zeros(0, 3, 150, 150), "empty"),
        (torch.full((1, 3, 150, 150), 200.0), "0..255"),
        (torch.full((1, 3, 150, 150), float("nan")), "NaN"),
    ],
)
def test_bad_inputs(model, bad, match):
    with pytest.raises(ValueError, match=match):
        model(bad)
    with pytest.raises(ValueError, match=match):
        model.features(bad)


def test_torch_matches_onnx_any_batch(built, model):
    session = onnx_session(built[0] / "dlib_resnet.onnx")
    assert [i.name for i in session.get_inputs()] == ["image"]
    assert [o.name for o in session.get_outputs()] == ["descriptor"]
    for batch in (1, 3):
        x = torch.rand(batch, 3, 150, 150, generator=torch.Generator().manual_seed(batch))
        with torch.no_grad():
            ref = model(x).numpy()
        got = session.run(["descriptor"], {"image": x.numpy()})[0]
        assert got.shape == (batch, 128)
        assert np.abs(ref - got).max() < 1e-4


# ----------------------------------------------------------------------------------------------
# gradients


def test_gradcheck_stem_and_blocks(model):
    w = {k: v.double() for k, v in model.named_buffers()}
    gen = torch.Generator().manual_seed(0)
    cases = [
        (lambda x: dr._stem(w, x), torch.rand(1, 3, 11, 11, generator=gen, dtype=torch.float64)),
        (lambda x: dr._residual_block(w, x, 0), torch.randn(1, 32, 3, 3, generator=gen, dtype=torch.float64)),
        # a downsampling block at 4 px: conv path 1x1, avg-pool shortcut 2x2 with half the channels,
        # so the sum zero-pads both ways, as at 8 px in the real network
        (lambda x: dr._residual_block(w, x, 3), torch.randn(1, 32, 4, 4, generator=gen, dtype=torch.float64)),
        (lambda a: dr._add_prev(a, torch.ones(1, 4, 3, 2, dtype=torch.float64)), torch.randn(1, 2, 4, 3, generator=gen, dtype=torch.float64)),
    ]
    for fn, x in cases:
        assert torch.autograd.gradcheck(fn, (x.requires_grad_(True),), eps=1e-6, atol=1e-5)


def test_full_network_directional_derivative(model):
    """The whole float64 network against a central finite difference along one random direction."""
    m64 = dr.DlibFaceDescriptor({k: v for k, v in model.named_buffers()}).double()
    gen = torch.Generator().manual_seed(1)
    x = (0.2 + 0.6 * torch.rand(1, 3, 150, 150, generator=gen, dtype=torch.float64)).requires_grad_(True)
    v = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    u = torch.randn(1, 128, generator=gen, dtype=torch.float64)
    (m64(x) * u).sum().backward()
    analytic = float((x.grad * v).sum())
    eps = 1e-8  # small: a larger step crosses ReLU / max-pool kinks somewhere in 67,500 inputs
    with torch.no_grad():
        numeric = float(((m64(x + eps * v) - m64(x - eps * v)) * u).sum() / (2 * eps))
    assert abs(analytic - numeric) <= 1e-5 * max(1.0, abs(numeric))


def test_gradients_reach_the_input_image(model):
    """Through the differentiable chip and the network, back to the full photo's pixels."""
    img = torch.rand(1, 3, 240, 260, generator=torch.Generator().manual_seed(2)).requires_grad_(True)
    unit = np.zeros((68, 2))
    unit[17:] = np.stack([fc._MEAN_FACE_X, fc._MEAN_FACE_Y], 1)  # only points 27.. are used
    lm = unit * 100 + [70.0, 60.0]
    affine = torch.from_numpy(face_chip_affine(lm))[None].float().requires_grad_(True)
    chip = extract_chip_torch(img, affine)
    f = model.features(chip)
    loss = f.descriptor.square().sum() + sum(a.mean() for a in f.activations)
    loss.backward()
    g = img.grad.abs().sum(1)[0]
    assert torch.isfinite(img.grad).all() and affine.grad is not None and torch.isfinite(affine.grad).all()
    assert g[60:160, 70:170].gt(0).float().mean() > 0.9  # the face region gets gradient
    assert g[:20, :20].sum() == 0  # outside the chip, none


# ----------------------------------------------------------------------------------------------
# dlib reference


@pytest.fixture(scope="module")
def dlib_faces():
    """(name, image, dlib shape, (68, 2) landmarks) for real photos, with dlib's own models."""
    dlib = pytest.importorskip("dlib")
    data = pytest.importorskip("skimage.data")
    from fitme_cli.perception.store import package_file

    sp = package_file("face-recognition-models", "face_recognition_models",
                      "models/shape_predictor_68_face_landmarks.dat", "CC0-1.0").path
    predictor, detector = dlib.shape_predictor(str(sp)), dlib.get_frontal_face_detector()
    astro = data.astronaut()
    camera = np.repeat(data.camera()[..., None], 3, 2)  # profile: dlib's detector misses it, so a fixed box
    faces = []
    for name, img, box in [("astronaut", astro, max(detector(astro, 1), key=lambda r: r.area())),
                           ("cameraman", camera, dlib.rectangle(175, 95, 265, 195))]:
        shape = predictor(img, box)
        faces.append((name, img, shape, np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)))
    return dlib.face_recognition_model_v1(str(dr.source_file().path)), faces


def test_matches_dlib_descriptor(built, model, dlib_faces):
    facerec, faces = dlib_faces
    refs = []
    for name, img, shape, lm in faces:
        ref = np.array(facerec.compute_face_descriptor(img, shape))
        ours = dr.face_descriptor_onnx(img, lm, built[0])
        assert ours.shape == (128,) and ours.dtype == np.float32
        with torch.no_grad():
            torch_desc = model(_chip_tensor(extract_chip(img, lm)))[0].numpy()
        assert np.abs(ours - ref).max() < 1e-4, name
        assert np.abs(torch_desc - ref).max() < 1e-4, name
        assert np.linalg.norm(ours - ref) < 1e-4, name
        refs.append(ref)
    # different people are far apart in dlib's metric (same person: < 0.6)
    assert np.linalg.norm(refs[0] - refs[1]) > 0.6


def test_network_alone_matches_dlib_on_chips(model, dlib_faces):
    """dlib's aligned-chip entry point isolates the network from the alignment."""
    facerec, faces = dlib_faces
    rng = np.random.default_rng(0)
    chips = [extract_chip(img, lm) for _, img, _, lm in faces] + [rng.integers(0, 256, (150, 150, 3), dtype=np.uint8)]
    with torch.no_grad():
        ours = model(torch.cat([_chip_tensor(c) for c in chips])).numpy()
    for chip, desc in zip(chips, ours):
        assert np.abs(desc - np.array(facerec.compute_face_descriptor(chip))).max() < 1e-4
