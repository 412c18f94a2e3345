"""Identity descriptors through the whole detect pipeline: transformed copies of a face stay closer to
the original than other real people do."""

import cv2
import numpy as np
import pytest

from fitme_cli.perception.detect import DetectSettings, detect

S = DetectSettings(identity=True)


@pytest.fixture(scope="module")
def roots(models_root):
    from fitme_cli.perception.registry import ensure_models

    return ensure_models(["dlib_resnet", "facenet"], models_root)


def _facenet(image, face, root):
    from fitme_cli.perception.facenet import facenet_embedding_onnx

    return facenet_embedding_onnx(image, face.landmarks.ibug68, root)


@pytest.fixture(scope="module")
def original(astronaut, roots):
    return detect(astronaut, S, roots).face.identity


@pytest.fixture(scope="module")
def original_facenet(astronaut, roots):
    return _facenet(astronaut, detect(astronaut, S, roots).face, roots)


@pytest.fixture(scope="module")
def other_people_facenet(roots):
    from fitme_cli.io import sample_photo

    out = []
    for name in ("camera", "grace_hopper"):
        rgb = sample_photo(name).rgb
        out.append(_facenet(rgb, detect(rgb, S, roots).face, roots))
    return out


@pytest.fixture(scope="module")
def other_people(roots):
    """Two other real people: the cameraman (grey, near-profile) and Grace Hopper (colour, frontal)."""
    from fitme_cli.io import sample_photo

    return [detect(sample_photo(name).rgb, S, roots).face.identity for name in ("camera", "grace_hopper")]


def _jpeg(img, q):
    ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, q])
    return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])


TRANSFORMS = {
    "flip": lambda im: np.ascontiguousarray(im[:, ::-1]),
    "crop": lambda im: np.ascontiguousarray(im[20:300, 90:330]),
    "rotate90": lambda im: np.ascontiguousarray(np.rot90(im)),
    "rotate25": lambda im: cv2.warpAffine(im, cv2.getRotationMatrix2D((225, 127), 25, 1.0), (512, 512)),
    "half": lambda im: cv2.resize(im, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA),
    "double": lambda im: cv2.resize(im, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC),
    "jpeg20": lambda im: _jpeg(im, 20),
    "dark": lambda im: (im * 0.4).astype(np.uint8),
    "bright": lambda im: np.clip(im * 1.5, 0, 255).astype(np.uint8),
    "gray": lambda im: np.repeat(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)[..., None], 3, axis=2),
}


def test_descriptor_shape(original):
    assert original.shape == (128,) and original.dtype == np.float32 and np.isfinite(original).all()


def test_different_people_are_far_apart(original, other_people):
    for other in other_people:
        assert np.linalg.norm(original - other) > 0.6  # dlib's same-person threshold


@pytest.mark.parametrize("name", TRANSFORMS)
def test_transformed_copy_stays_closer_than_another_person(name, astronaut, roots, original, other_people):
    emb = detect(TRANSFORMS[name](astronaut), S, roots).face.identity
    same = np.linalg.norm(emb - original)
    assert same < 0.6, f"{name}: {same:.3f}"
    assert all(same < np.linalg.norm(emb - other) for other in other_people)


@pytest.mark.parametrize("name", TRANSFORMS)
def test_evaluation_network_agrees(name, astronaut, roots, original_facenet, other_people_facenet):
    """The same, judged by FaceNet (the evaluation network) on its own eye-levelled crops."""
    img = TRANSFORMS[name](astronaut)
    emb = _facenet(img, detect(img, S, roots).face, roots)
    same = float(emb @ original_facenet)
    assert same > 0.7, f"{name}: {same:.3f}"
    assert all(same > float(emb @ other) + 0.3 for other in other_people_facenet)
