"""dlib's ResNet face descriptor (``dlib_face_recognition_resnet_model_v1.dat``) in torch and ONNX.

The ``.dat`` is read in pure numpy (format notes in docs/dlib_resnet.md). The network is dlib's
``anet_type``: a 7x7/2 conv stem, 3x3/2 max pool, 14 residual blocks (29 conv + affine layers in
all), global average pool and a 128-d linear projection, on 150x150 RGB chips cut by
``face_chip.extract_chip``. Descriptors of one person lie within ~0.6 (euclidean) of each other.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ModelBuildError
from .frozen_net import check_image_batch, register_weights
from .store import SourceFile, atomic_write_bytes, load_tensors, save_tensors, write_card

__all__ = [
    "NAME",
    "INPUT_SIZE",
    "source_file",
    "read_dlib_resnet",
    "dlib_resnet_features",
    "DescriptorFeatures",
    "DlibFaceDescriptor",
    "build",
    "load_dlib_resnet",
    "face_descriptor_onnx",
]

NAME = "dlib_resnet"
INPUT_SIZE = 150
_INPUT_SCALE = 256.0  # dlib's input_rgb_image: (pixel - mean) / 256, pixel in 0..255

# The 14 residual blocks, input to output: (channels, first conv stride). Stride 2 blocks are
# dlib's ares_down; their shortcut is a 2x2/2 average pool, zero-padded to the block's shape.
BLOCKS: tuple[tuple[int, int], ...] = (
    (32, 1), (32, 1), (32, 1),
    (64, 2), (64, 1), (64, 1), (64, 1),
    (128, 2), (128, 1), (128, 1),
    (256, 2), (256, 1), (256, 1),
    (256, 2),
)
# Blocks after which ``features`` reports an activation (the end of each of dlib's levels).
_LEVEL_ENDS = (2, 6, 9, 12, 13)


def source_file() -> SourceFile:
    from .registry import MODELS  # the one place that names each model's source package

    return MODELS[NAME].source()


# ----------------------------------------------------------------------------------------------
# the .dat parser


class _Reader:
    """dlib's serialisation: integers as a control byte (low nibble: byte count, bit 7: sign) plus
    little-endian bytes; floats as an integer mantissa and exponent; bools as '0'/'1'; strings
    length-prefixed; tensors as version 2, four dims, then raw little-endian float32."""

    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    def _need(self, n: int) -> None:
        if self.pos + n > len(self.data):
            raise ModelBuildError(f"truncated dlib file at byte {self.pos}")

    def int(self) -> int:
        self._need(1)
        ctrl = self.data[self.pos]
        n = ctrl & 0x0F
        if n > 8:
            raise ModelBuildError(f"bad integer control byte 0x{ctrl:02x} at byte {self.pos}")
        self._need(1 + n)
        v = int.from_bytes(self.data[self.pos + 1 : self.pos + 1 + n], "little")
        self.pos += 1 + n
        return -v if ctrl & 0x80 else v

    def float(self) -> float:
        mantissa, exponent = self.int(), self.int()
        if abs(exponent) >= 32000:  # dlib's markers for inf / nan
            raise ModelBuildError("non-finite scalar in dlib file")
        return float(mantissa * 2.0**exponent)

    def bool(self) -> bool:
        self._need(1)
        c = self.data[self.pos : self.pos + 1]
        if c not in (b"0", b"1"):
            raise ModelBuildError(f"bad bool {c!r} at byte {self.pos}")
        self.pos += 1
        return c == b"1"

    def str(self) -> str:
        n = self.int()
        self._need(n)
        s = self.data[self.pos : self.pos + n].decode("latin-1")
        self.pos += n
        return s

    def dims(self, count: int, version: int) -> list[int]:
        v = self.int()
        if v != version:
            raise ModelBuildError(f"unexpected version {v} at byte {self.pos}")
        return [self.int() for _ in range(count)]

    def skip_floats(self, count: int) -> None:
        for _ in range(count):
            self.float()

    def tensor(self) -> np.ndarray:
        shape = self.dims(4, version=2)
        if min(shape) < 0:
            raise ModelBuildError(f"negative tensor dimension at byte {self.pos}")
        n = int(np.prod(shape))
        self._need(4 * n)
        a = np.frombuffer(self.data, "<f4", n, self.pos).astype(np.float32)
        self.pos += 4 * n
        return a


def _layer_details(r: _Reader) -> dict[str, Any]:
    """One layer's details plus add_layer's bookkeeping (3 bools, 3 empty tensors)."""
    kind = r.str()
    d: dict[str, Any] = {"kind": kind}
    if kind == "con_4":
        d["params"] = r.tensor()
        d["filters"], d["nr"], d["nc"], d["stride_y"], d["stride_x"], d["pad_y"], d["pad_x"] = (r.int() for _ in range(7))
        d["filter_shape"], _ = r.dims(4, 1), r.dims(4, 1)  # alias tensors: filters, biases
        r.skip_floats(4)  # learning-rate and weight-decay multipliers
    elif kind == "affine_":
        d["params"] = r.tensor()
        r.dims(4, 1), r.dims(4, 1)  # gamma, beta
        d["mode"] = r.int()
    elif kind in ("max_pool_2", "avg_pool_2"):
        d["nr"], d["nc"], d["stride_y"], d["stride_x"], d["pad_y"], d["pad_x"] = (r.int() for _ in range(6))
    elif kind == "fc_2":
        d["outputs"], d["inputs"] = r.int(), r.int()
        d["params"] = r.tensor()
        r.dims(4, 1), r.dims(4, 1)  # weights, biases
        d["bias_mode"] = r.int()
        r.skip_floats(4)
    elif kind not in ("relu_", "add_prev_"):
        raise ModelBuildError(f"unsupported dlib layer {kind!r}")
    for _ in range(3):  # setup called, gradient stale, output disabled
        r.bool()
    for _ in range(3):  # x_grad, cached_output, params_grad: empty in a saved net
        r.tensor()
    return d


def _parse_layers(data: bytes) -> tuple[list[dict[str, Any]], np.ndarray]:
    """Layers from the input upward (tags and skips as {'kind': 'tag'}), and the input mean."""
    r = _Reader(data)
    if r.int() != 1 or r.str() != "loss_metric_2":
        raise ModelBuildError("not a dlib loss_metric network")
    r.float(), r.float()  # margin, distance threshold
    # add_layer writes its version, then its subnet, then its own details: the versions of all
    # layers come first, outermost first (2: layer, 1: tag/skip, 3: the layer on the input).
    versions = []
    while True:
        v = r.int()
        if v not in (1, 2, 3):
            raise ModelBuildError(f"unexpected layer version {v} at byte {r.pos}")
        versions.append(v)
        if v == 3:
            break
    if r.str() != "input_rgb_image_sized":
        raise ModelBuildError("expected an input_rgb_image_sized input layer")
    mean = np.array([r.float(), r.float(), r.float()], np.float32)
    if (r.int(), r.int()) != (INPUT_SIZE, INPUT_SIZE):
        raise ModelBuildError(f"expected a {INPUT_SIZE}x{INPUT_SIZE} input layer")
    layers = [_layer_details(r)]
    r.int()  # sample expansion factor of the input add_layer
    for v in reversed(versions[:-1]):
        layers.append(_layer_details(r) if v == 2 else {"kind": "tag"})
    if r.pos != len(data):
        raise ModelBuildError(f"{len(data) - r.pos} trailing bytes in dlib file")
    return layers, mean


def _expected_kinds() -> list[str]:
    seq = ["con_4", "affine_", "relu_", "max_pool_2"]
    for _, stride in BLOCKS:
        body = ["tag", "con_4", "affine_", "relu_", "con_4", "affine_"]
        seq += body + (["tag", "tag", "avg_pool_2"] if stride == 2 else []) + ["add_prev_", "relu_"]
    return seq + ["avg_pool_2", "fc_2"]


def _conv(d: dict[str, Any], cin: int, cout: int, k: int, stride: int, pad: int, name: str) -> dict[str, np.ndarray]:
    got = (d["filters"], d["nr"], d["nc"], d["stride_y"], d["stride_x"], d["pad_y"], d["pad_x"])
    if got != (cout, k, k, stride, stride, pad, pad) or d["filter_shape"] != [cout, cin, k, k]:
        raise ModelBuildError(f"{name}: unexpected conv {got} {d['filter_shape']}")
    n = cout * cin * k * k
    p = d["params"]
    if p.size != n + cout:
        raise ModelBuildError(f"{name}: expected {n + cout} conv parameters, got {p.size}")
    return {f"{name}.weight": p[:n].reshape(cout, cin, k, k), f"{name}.bias": p[n:]}


def _affine(d: dict[str, Any], c: int, name: str) -> dict[str, np.ndarray]:
    if d["mode"] != 0 or d["params"].size != 2 * c:  # 0: CONV_MODE, one gamma/beta per channel
        raise ModelBuildError(f"{name}: unexpected affine layer")
    return {f"{name}.gamma": d["params"][:c], f"{name}.beta": d["params"][c:]}


def read_dlib_resnet(path: Path) -> dict[str, np.ndarray]:
    """Parse the ``.dat`` into named float32 tensors (torch layouts: conv OIHW, linear (out, in)).

    Names: ``input.mean`` (3,), ``stem.conv``/``stem.affine``, ``blocks.{i}.conv1|affine1|conv2|affine2``
    (``.weight``/``.bias``, ``.gamma``/``.beta``) and ``fc.weight`` (128, 256). The layer sequence and
    every conv/pool hyper-parameter are checked against the architecture this module implements.
    """
    layers, mean = _parse_layers(Path(path).read_bytes())
    kinds = [d["kind"] for d in layers]
    if kinds != _expected_kinds():
        raise ModelBuildError("dlib network layout differs from dlib_face_recognition_resnet_model_v1")
    for d in layers:
        if d["kind"] == "max_pool_2" and (d["nr"], d["nc"], d["stride_y"], d["stride_x"], d["pad_y"], d["pad_x"]) != (3, 3, 2, 2, 0, 0):
            raise ModelBuildError("unexpected max pool")
        if d["kind"] == "avg_pool_2" and (d["stride_y"], d["pad_y"], d["pad_x"]) not in ((2, 0, 0), (1, 0, 0)):
            raise ModelBuildError("unexpected average pool")
    it = iter(d for d in layers if d["kind"] in ("con_4", "affine_", "fc_2"))
    out: dict[str, np.ndarray] = {"input.mean": mean}
    out |= _conv(next(it), 3, 32, 7, 2, 0, "stem.conv")
    out |= _affine(next(it), 32, "stem.affine")
    cin = 32
    for i, (c, stride) in enumerate(BLOCKS):
        out |= _conv(next(it), cin, c, 3, stride, 0 if stride == 2 else 1, f"blocks.{i}.conv1")
        out |= _affine(next(it), c, f"blocks.{i}.affine1")
        out |= _conv(next(it), c, c, 3, 1, 1, f"blocks.{i}.conv2")
        out |= _affine(next(it), c, f"blocks.{i}.affine2")
        cin = c
    fc = next(it)
    if (fc["outputs"], fc["inputs"], fc["bias_mode"], fc["params"].size) != (128, 256, 1, 128 * 256):
        raise ModelBuildError("unexpected fc_no_bias layer")
    out["fc.weight"] = fc["params"].reshape(256, 128).T.copy()  # dlib stores (inputs, outputs)
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}


# ----------------------------------------------------------------------------------------------
# the network, as plain functions of a weight mapping


def _conv_affine(w: Mapping[str, torch.Tensor], x: torch.Tensor, conv: str, affine: str, stride: int) -> torch.Tensor:
    # dlib's con_ pads (k-1)/2 at stride 1 and nothing at stride 2 (its template default).
    weight = w[f"{conv}.weight"]
    pad = 0 if stride != 1 else weight.shape[-1] // 2
    y = F.conv2d(x, weight, w[f"{conv}.bias"], stride=stride, padding=pad)
    return y * w[f"{affine}.gamma"][:, None, None] + w[f"{affine}.beta"][:, None, None]


def _add_prev(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """dlib's add_prev: the sum over the larger of each dim, missing elements zero (top-left aligned)."""
    c, h, wd = (max(a.shape[i], b.shape[i]) for i in (1, 2, 3))

    def grow(t: torch.Tensor) -> torch.Tensor:
        if t.shape[1:] == (c, h, wd):
            return t
        return F.pad(t, (0, wd - t.shape[3], 0, h - t.shape[2], 0, c - t.shape[1]))

    return grow(a) + grow(b)


def _stem(w: Mapping[str, torch.Tensor], image: torch.Tensor) -> torch.Tensor:
    mean = w["input.mean"].to(image.dtype)[:, None, None]
    x = (image * 255.0 - mean) / _INPUT_SCALE
    x = F.relu(_conv_affine(w, x, "stem.conv", "stem.affine", 2))
    return F.max_pool2d(x, 3, 2)


def _residual_block(w: Mapping[str, torch.Tensor], x: torch.Tensor, i: int) -> torch.Tensor:
    stride = BLOCKS[i][1]
    y = F.relu(_conv_affine(w, x, f"blocks.{i}.conv1", f"blocks.{i}.affine1", stride))
    y = _conv_affine(w, y, f"blocks.{i}.conv2", f"blocks.{i}.affine2", 1)
    shortcut = F.avg_pool2d(x, 2, 2) if stride == 2 else x
    return F.relu(_add_prev(shortcut, y))


def dlib_resnet_features(w: Mapping[str, torch.Tensor], image: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The forward pass: image (B, 3, 150, 150) RGB in [0, 1] -> descriptor (B, 128) and the
    activations after the stem and after each of dlib's five levels (35, 35, 17, 8, 4, 2 px)."""
    x = _stem(w, image)
    acts = [x]
    for i in range(len(BLOCKS)):
        x = _residual_block(w, x, i)
        if i in _LEVEL_ENDS:
            acts.append(x)
    return F.linear(x.mean(dim=(2, 3)), w["fc.weight"]), acts


@dataclass(frozen=True)
class DescriptorFeatures:
    descriptor: torch.Tensor  # (B, 128)
    activations: list[torch.Tensor]  # stem, then the end of each level: (B, C, H, W)


def _check_image(image: Any) -> None:
    check_image_batch(image, INPUT_SIZE)


class DlibFaceDescriptor(nn.Module):
    """dlib's face descriptor as a frozen torch module, differentiable with respect to its input.

    ``forward(image)``: image (B, 3, 150, 150) float RGB in [0, 1], an aligned dlib face chip
    (``face_chip.extract_chip`` / ``extract_chip_torch``) -> (B, 128) descriptor, same dtype.
    Weights are buffers, so ``.double()`` / ``.to(device)`` carry them and nothing trains them.
    """

    def __init__(self, weights: Mapping[str, np.ndarray | torch.Tensor]):
        super().__init__()
        missing = set(_weight_names()) - set(weights)
        if missing:
            raise ValueError(f"missing weights: {sorted(missing)[:5]}")
        register_weights(self, weights)
        self.eval()

    def _weights(self) -> dict[str, torch.Tensor]:
        return dict(self.named_buffers())

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        _check_image(image)
        return dlib_resnet_features(self._weights(), image)[0]

    def features(self, image: torch.Tensor) -> DescriptorFeatures:
        """Descriptor plus intermediate activations, for a perceptual (identity-feature) loss."""
        _check_image(image)
        desc, acts = dlib_resnet_features(self._weights(), image)
        return DescriptorFeatures(desc, acts)


def _weight_names() -> list[str]:
    names = ["input.mean", "stem.conv.weight", "stem.conv.bias", "stem.affine.gamma", "stem.affine.beta", "fc.weight"]
    for i in range(len(BLOCKS)):
        for j in (1, 2):
            names += [f"blocks.{i}.conv{j}.weight", f"blocks.{i}.conv{j}.bias", f"blocks.{i}.affine{j}.gamma", f"blocks.{i}.affine{j}.beta"]
    return names


def load_dlib_resnet(models_dir: Path) -> DlibFaceDescriptor:
    """The torch module from ``models_dir/dlib_resnet.safetensors`` (ModelMissing if not built)."""
    return DlibFaceDescriptor(load_tensors(Path(models_dir) / f"{NAME}.safetensors"))


# ----------------------------------------------------------------------------------------------
# build


def _reference_chip() -> tuple[np.ndarray | None, str]:
    """A real face, 150x150 uint8, for the torch-vs-ONNX check: the astronaut's face from
    scikit-image (a test dependency) when installed, cropped and resized (no landmarks needed)."""
    try:
        import cv2
        from skimage import data
    except ImportError:
        return None, "scikit-image not installed"
    img = data.astronaut()
    crop = img[50:200, 150:300]  # roughly dlib's chip box around her face
    return cv2.resize(crop, (INPUT_SIZE, INPUT_SIZE), interpolation=cv2.INTER_AREA), "skimage.data.astronaut face crop"


def _export_onnx(model: DlibFaceDescriptor) -> bytes:
    from .onnx_export import export_onnx

    return export_onnx(model, torch.rand(1, 3, INPUT_SIZE, INPUT_SIZE), "image", ["descriptor"])


def build(out_dir: Path) -> dict[str, Any]:
    """Convert the ``.dat`` into ``dlib_resnet.{safetensors,onnx,json}`` in ``out_dir`` (overwrites
    atomically) and return the card, with the measured torch-vs-ONNX differences."""
    from .onnx_runner import onnx_session

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    source = source_file()
    weights = read_dlib_resnet(source.path)
    save_tensors(out_dir / f"{NAME}.safetensors", weights)
    model = DlibFaceDescriptor(weights)
    atomic_write_bytes(out_dir / f"{NAME}.onnx", _export_onnx(model))

    session = onnx_session(out_dir / f"{NAME}.onnx")
    gen = torch.Generator().manual_seed(0)
    inputs = {"random": torch.rand(4, 3, INPUT_SIZE, INPUT_SIZE, generator=gen)}
    chip, chip_source = _reference_chip()
    if chip is not None:
        inputs["real_chip"] = torch.from_numpy(chip).permute(2, 0, 1)[None].float() / 255.0
    checks: dict[str, Any] = {"real_chip_source": chip_source}
    with torch.no_grad():
        for key, x in inputs.items():
            ref = model(x).numpy()
            got = session.run(["descriptor"], {"image": x.numpy()})[0]
            checks[f"max_abs_torch_minus_onnx_{key}"] = float(np.abs(ref - got).max())
    worst = max(v for k, v in checks.items() if k.startswith("max_abs"))
    if worst > 1e-3:
        raise ModelBuildError(f"ONNX export of {NAME} disagrees with torch by {worst:.3g}")
    checks["max_abs_torch_minus_onnx"] = worst

    card: dict[str, Any] = {
        "name": NAME,
        "kind": "dlib",
        "source": source.describe(),
        "licence": source.licence,
        "input": {
            "name": "image", "shape": ["B", 3, INPUT_SIZE, INPUT_SIZE], "dtype": "float32",
            "layout": "NCHW RGB", "range": [0.0, 1.0],
            "alignment": "dlib face chip: 68 iBUG landmarks, size 150, padding 0.25 (face_chip.extract_chip)",
            "normalisation": {"mean_rgb_0_255": weights["input.mean"].tolist(), "scale": _INPUT_SCALE},
        },
        "outputs": ["descriptor"],
        "output": {"name": "descriptor", "shape": ["B", 128], "same_person_euclidean_below": 0.6},
        "spec": {"blocks": [list(b) for b in BLOCKS], "conv_affine_layers": 1 + 2 * len(BLOCKS)},
        "checks": checks,
        "build_seconds": round(time.perf_counter() - t0, 2),
    }
    write_card(out_dir / f"{NAME}.json", card)
    return card


# ----------------------------------------------------------------------------------------------
# inference


def face_descriptor_onnx(image_rgb: np.ndarray, landmarks68: np.ndarray, models_dir: Path, threads: int = 0) -> np.ndarray:
    """dlib's ``compute_face_descriptor(img, shape)`` with our chip and ONNX model: (128,) float32.

    ``image_rgb`` uint8 (H, W, 3); ``landmarks68`` (68, 2) (x, y) pixels, iBUG order.
    """
    from .face_chip import extract_chip
    from .onnx_runner import onnx_session

    chip = extract_chip(image_rgb, landmarks68, INPUT_SIZE, 0.25)
    x = (chip.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
    session = onnx_session(Path(models_dir) / f"{NAME}.onnx", threads)
    return session.run(["descriptor"], {"image": np.ascontiguousarray(x)})[0][0]
