"""TFLite -> torch conversion: values against the LiteRT interpreter and onnxruntime, float64 gradients."""

import numpy as np
import pytest
import torch

from fitme_cli.perception.registry import MODELS
from fitme_cli.perception.tflite_convert import load_tflite_net
from fitme_cli.perception.tflite_graph import TfliteGraph, TfliteOp, read_tflite
from fitme_cli.perception.tflite_net import TfliteNet, _same_pads

TFLITE_MODELS = ["blazeface_short", "blazeface_full", "facemesh"]


@pytest.mark.parametrize("name", TFLITE_MODELS)
def test_torch_matches_onnx_and_litert(name, models_root):
    from fitme_cli.perception.onnx_runner import onnx_session

    litert = pytest.importorskip("ai_edge_litert.interpreter")
    net = load_tflite_net(models_root, name)
    _, h, w, c = net.graph.shapes[net.graph.inputs[0]]
    x = np.random.default_rng(1).uniform(-1, 1, (1, h, w, c)).astype(np.float32)
    with torch.no_grad():
        ours = [o.numpy() for o in net(torch.from_numpy(x).permute(0, 3, 1, 2).contiguous())]
    onnx = onnx_session(models_root / f"{name}.onnx").run(None, {"image": x.transpose(0, 3, 1, 2).copy()})
    interp = litert.Interpreter(model_path=str(MODELS[name].source().path))
    interp.allocate_tensors()
    interp.set_tensor(interp.get_input_details()[0]["index"], x)
    interp.invoke()
    out_names = [net.graph.names[i] for i in net.graph.outputs]
    for det in interp.get_output_details():
        j = out_names.index(det["name"])
        ref = interp.get_tensor(det["index"])
        scale = np.abs(ref).max()
        assert ours[j].shape == ref.shape
        assert np.abs(ours[j] - onnx[j]).max() <= 1e-5 * scale + 1e-5
        assert np.abs(ours[j] - ref).max() <= 1e-5 * scale + 1e-5, f"{name}/{det['name']}"


def test_batched_onnx_matches_single(models_root):
    from fitme_cli.perception.onnx_runner import onnx_session

    x = np.random.default_rng(2).uniform(0, 1, (3, 3, 192, 192)).astype(np.float32)
    sess = onnx_session(models_root / "facemesh.onnx")
    batched = sess.run(None, {"image": x})[0]
    single = np.concatenate([sess.run(None, {"image": x[i : i + 1]})[0] for i in range(3)])
    assert np.allclose(batched, single, atol=1e-4)


def test_gradients_reach_the_input(models_root):
    net = load_tflite_net(models_root, "facemesh")
    x = torch.rand(1, 3, 192, 192, requires_grad=True)
    landmarks, _ = net(x)
    landmarks.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def _tiny_graph() -> TfliteGraph:
    """Every supported op, on an 8x8 input: conv (SAME, stride 2), depthwise, PReLU, max-pool, channel
    PAD, ADD, RELU, RESIZE_BILINEAR, CONCATENATION, RESHAPE."""
    rng = np.random.default_rng(0)
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    shapes = {0: (1, 8, 8, 3), 1: (4, 3, 3, 3), 2: (4,), 3: (1, 4, 4, 4), 4: (1, 3, 3, 4), 5: (4,), 6: (1, 4, 4, 4),
              7: (4,), 8: (1, 4, 4, 4), 9: (1, 2, 2, 4), 10: (4, 2), 11: (1, 2, 2, 6), 12: (1, 2, 2, 6),
              13: (1, 2, 2, 6), 14: (2,), 15: (1, 4, 4, 6), 16: (1, 4, 4, 10), 17: (3,), 18: (1, 16, 10)}
    consts = {1: f(4, 3, 3, 3), 2: f(4), 4: f(1, 3, 3, 4), 5: f(4), 7: np.abs(f(4)) * 0.2,
              10: np.array([[0, 0], [0, 0], [0, 0], [1, 1]], np.int64), 12: f(1, 2, 2, 6),
              14: np.array([4, 4], np.int64), 17: np.array([1, 16, 10], np.int64)}
    ops = (
        TfliteOp("CONV_2D", (0, 1, 2), (3,), {"padding": "same", "stride": [2, 2], "dilation": [1, 1], "activation": "none"}),
        TfliteOp("DEPTHWISE_CONV_2D", (3, 4, 5), (6,), {"padding": "same", "stride": [1, 1], "dilation": [1, 1], "depth_multiplier": 1, "activation": "relu"}),
        TfliteOp("PRELU", (3, 7), (8,), {}),
        TfliteOp("MAX_POOL_2D", (8,), (9,), {"padding": "valid", "stride": [2, 2], "kernel": [2, 2], "activation": "none"}),
        TfliteOp("PAD", (9, 10), (11,), {}),
        TfliteOp("ADD", (11, 12), (13,), {"activation": "relu"}),
        TfliteOp("RESIZE_BILINEAR", (13, 14), (15,), {"align_corners": False, "half_pixel_centers": True}),
        TfliteOp("CONCATENATION", (15, 6), (16,), {"axis": 3, "activation": "none"}),
        TfliteOp("RESHAPE", (16, 17), (18,), {}),
    )
    return TfliteGraph(ops, shapes, {i: f"t{i}" for i in shapes}, (0,), (18,), consts)


def test_tiny_graph_gradcheck_float64():
    net = TfliteNet(_tiny_graph()).double()
    x = torch.randn(2, 3, 8, 8, dtype=torch.float64, requires_grad=True)
    assert net(x)[0].shape == (2, 16, 10)
    assert torch.autograd.gradcheck(lambda t: net(t)[0], (x,), eps=1e-6, atol=1e-5)


def _conv_same_reference(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int) -> np.ndarray:
    """The slow, obvious NHWC convolution with TF 'SAME' padding: x (H, W, C), w (O, kh, kw, C)."""
    h, wd, _ = x.shape
    o, kh, kw, _ = w.shape
    top, _ = _same_pads(h, kh, stride, 1)
    left, _ = _same_pads(wd, kw, stride, 1)
    oh, ow = -(-h // stride), -(-wd // stride)
    out = np.zeros((oh, ow, o))
    for i in range(oh):
        for j in range(ow):
            for di in range(kh):
                for dj in range(kw):
                    y, xx = i * stride + di - top, j * stride + dj - left
                    if 0 <= y < h and 0 <= xx < wd:
                        out[i, j] += w[:, di, dj, :] @ x[y, xx]
    return out + b


def test_tiny_graph_known_values_and_nhwc_flattening():
    """NHWC semantics survive NCHW execution: the final RESHAPE flattens in TFLite's channel-last order,
    so its last 4 values per pixel are the depthwise branch, and the conv matches the slow reference."""
    g = _tiny_graph()
    net = TfliteNet(g)
    x = torch.randn(1, 3, 8, 8)
    out = net(x)[0].reshape(1, 4, 4, 10)
    conv = _conv_same_reference(x[0].permute(1, 2, 0).double().numpy(), g.constants[1], g.constants[2], 2)
    w, b = g.constants[4][0], g.constants[5]  # depthwise (3, 3, 4), then fused ReLU
    pad = np.pad(conv, ((1, 1), (1, 1), (0, 0)))
    dw = np.maximum(sum(pad[i : i + 4, j : j + 4] * w[i, j] for i in range(3) for j in range(3)) + b, 0)
    assert np.allclose(out[0, ..., 6:].numpy(), dw, atol=1e-4)


def test_same_padding_matches_tensorflow_rule():
    assert _same_pads(128, 5, 2, 1) == (1, 2)  # TF puts the odd pixel after
    assert _same_pads(8, 3, 1, 1) == (1, 1)
    assert _same_pads(7, 1, 1, 1) == (0, 0)


def test_input_shape_is_checked():
    net = TfliteNet(_tiny_graph())
    with pytest.raises(ValueError, match=r"expected input of shape \(B, 3, 8, 8\), got \(1, 8, 8, 3\)"):
        net(torch.zeros(1, 8, 8, 3))


def test_unsupported_op_is_named(tmp_path):
    from fitme_cli.errors import ModelBuildError

    g = _tiny_graph()
    bad = TfliteGraph(g.ops + (TfliteOp("SOFTMAX", (18,), (19,), {}),), {**g.shapes, 19: (1, 16, 10)}, g.names, g.inputs, (19,), g.constants)
    with pytest.raises(ModelBuildError, match="SOFTMAX"):
        TfliteNet(bad)(torch.zeros(1, 3, 8, 8))


def test_reader_folds_fp16_weights():
    g = read_tflite(MODELS["blazeface_short"].source().path)
    kinds = {op.kind for op in g.ops}
    assert "DEQUANTIZE" not in kinds and {"CONV_2D", "DEPTHWISE_CONV_2D", "PAD"} <= kinds
    assert all(v.dtype in (np.float32, np.int32, np.int64) for v in g.constants.values())
