"""Detection and landmarks on a real photo (scikit-image's astronaut) and transformed copies of it:
landmarks stay on the face and move consistently with each transform."""

import cv2
import numpy as np
import pytest

from fitme_cli.perception.detect import DetectSettings, detect, detect_faces

S = DetectSettings(identity=False)
MIDLINE = [10, 151, 9, 8, 168, 6, 197, 195, 5, 4, 1, 19, 94, 2, 164, 0, 11, 12, 13, 14, 15, 16, 17, 18, 200, 199, 175, 152]


@pytest.fixture(scope="module")
def reference(astronaut, models_root):
    return detect(astronaut, S, models_root)


def _mean_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=-1).mean())


def _face_size(det) -> float:
    b = det.face.detection.box
    return float(b[2] - b[0])


def test_landmarks_on_the_face(reference):
    f = reference.face
    # hand-checked in the overlay: the face spans about x 178-272, y 80-175 in the 512x512 photo
    assert 170 < f.detection.box[0] < 190 and 260 < f.detection.box[2] < 285
    pts = f.landmarks.points
    assert pts.shape == (468, 3) and pts.dtype == np.float32
    assert np.all((pts[:, 0] > 160) & (pts[:, 0] < 290) & (pts[:, 1] > 50) & (pts[:, 1] < 190))
    assert f.landmarks.presence > 0.9 and f.detection.score > 0.8
    p = f.landmarks.pose
    assert abs(p.yaw) < 10 and abs(p.pitch) < 15 and abs(p.roll) < 10
    # left and right eye outer corners on the correct sides, eyes above the mouth
    assert pts[33, 0] < pts[263, 0] and pts[33, 1] < pts[13, 1]


def test_ibug68_agrees_with_dlib_shape_predictor(reference, astronaut):
    """Independent check of the 468 -> 68 mapping: dlib's own 68-point predictor on the same face."""
    dlib = pytest.importorskip("dlib")
    import importlib.util
    from pathlib import Path

    root = Path(importlib.util.find_spec("face_recognition_models").submodule_search_locations[0])
    pred = dlib.shape_predictor(str(root / "models" / "shape_predictor_68_face_landmarks.dat"))
    rect = dlib.get_frontal_face_detector()(astronaut, 1)[0]
    ref = np.array([[p.x, p.y] for p in pred(astronaut, rect).parts()], float)
    ours = reference.face.landmarks.ibug68
    iod = np.linalg.norm(ref[36:42].mean(0) - ref[42:48].mean(0))
    err = np.linalg.norm(ours - ref, axis=1) / iod
    assert err.mean() < 0.07
    assert err[36:68].mean() < 0.05  # eyes and mouth: well-defined points
    assert err.max() < 0.2


def test_flip(reference, astronaut, models_root):
    w = astronaut.shape[1]
    det = detect(np.ascontiguousarray(astronaut[:, ::-1]), S, models_root)
    mirrored = reference.face.landmarks.points[MIDLINE, :2] * [-1, 1] + [w - 1, 0]
    assert _mean_err(det.face.landmarks.points[MIDLINE, :2], mirrored) < 0.03 * _face_size(reference)
    p0, p1 = reference.face.landmarks.pose, det.face.landmarks.pose
    assert p1.yaw == pytest.approx(-p0.yaw, abs=3) and p1.roll == pytest.approx(-p0.roll, abs=2)
    assert p1.pitch == pytest.approx(p0.pitch, abs=3)


@pytest.mark.parametrize("x0,y0", [(100, 20), (150, 60)])
def test_crop(reference, astronaut, models_root, x0, y0):
    det = detect(np.ascontiguousarray(astronaut[y0 : y0 + 260, x0 : x0 + 240]), S, models_root)
    expect = reference.face.landmarks.points[:, :2] - [x0, y0]
    assert _mean_err(det.face.landmarks.points[:, :2], expect) < 0.03 * _face_size(reference)


@pytest.mark.parametrize("k", [0.5, 2.0, 4.0])
def test_scale(reference, astronaut, models_root, k):
    img = cv2.resize(astronaut, None, fx=k, fy=k, interpolation=cv2.INTER_AREA if k < 1 else cv2.INTER_CUBIC)
    det = detect(img, S, models_root)
    expect = (reference.face.landmarks.points[:, :2] + 0.5) * k - 0.5
    assert _mean_err(det.face.landmarks.points[:, :2], expect) < 0.03 * _face_size(reference) * k


@pytest.mark.parametrize("angle", [20, -45, 90, -90, 180, 75])
def test_in_plane_rotation(reference, astronaut, models_root, angle):
    """Rotate about the face centre; the whole photo is padded so nothing is cut."""
    big = cv2.copyMakeBorder(astronaut, 256, 256, 256, 256, cv2.BORDER_CONSTANT)
    c = (256 + 225.0, 256 + 127.0)
    m = cv2.getRotationMatrix2D(c, angle, 1.0)  # positive = counter-clockwise on screen
    img = cv2.warpAffine(big, m, (big.shape[1], big.shape[0]), flags=cv2.INTER_LINEAR)
    det = detect(img, S, models_root)
    pts = reference.face.landmarks.points[:, :2] + 256
    expect = pts @ m[:, :2].T + m[:, 2]
    assert _mean_err(det.face.landmarks.points[:, :2], expect) < 0.05 * _face_size(reference)
    roll = det.face.landmarks.pose.roll - reference.face.landmarks.pose.roll
    assert (roll + angle + 180) % 360 - 180 == pytest.approx(0, abs=5)


@pytest.mark.parametrize("quality", [50, 15])
def test_jpeg(reference, astronaut, models_root, quality):
    ok, buf = cv2.imencode(".jpg", astronaut[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    img = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
    det = detect(img, S, models_root)
    assert _mean_err(det.face.landmarks.points[:, :2], reference.face.landmarks.points[:, :2]) < 0.03 * _face_size(reference)


@pytest.mark.parametrize("gain,gamma", [(0.35, 1.0), (1.0, 0.5), (1.6, 1.0)])
def test_brightness(reference, astronaut, models_root, gain, gamma):
    img = np.clip(255 * (astronaut / 255.0) ** gamma * gain, 0, 255).astype(np.uint8)
    det = detect(img, S, models_root)
    assert _mean_err(det.face.landmarks.points[:, :2], reference.face.landmarks.points[:, :2]) < 0.03 * _face_size(reference)


def _srgb_to_lin(img: np.ndarray) -> np.ndarray:
    """uint8 sRGB -> float linear, with the map I/O's curve."""
    from fitme_cli.io.maps import srgb_to_linear

    return srgb_to_linear(img / 255.0)


def _lin_to_srgb(x: np.ndarray) -> np.ndarray:
    from fitme_cli.io.maps import linear_to_srgb

    return np.round(255 * linear_to_srgb(x)).astype(np.uint8)


def _retone(photo: np.ndarray, det, level: int) -> np.ndarray:
    """The photo with the face's skin (inside the landmarks' hull, eyes and mouth kept) scaled in linear
    RGB so its median becomes Monk Skin Tone ``level``'s swatch, at the photo's exposure (taken as MST 6's)."""
    from fitme_cli.reflectance.augment import monk_albedo

    mask = np.zeros(photo.shape[:2], np.float32)
    cv2.fillConvexPoly(mask, cv2.convexHull(det.face.landmarks.points[:, :2].astype(np.int32)), 1.0)
    i68 = det.face.landmarks.ibug68
    for part in (i68[36:42], i68[42:48], i68[60:68]):
        cv2.fillConvexPoly(mask, cv2.convexHull(part.astype(np.int32)), 0.0)
    mask = cv2.GaussianBlur(mask, (0, 0), 3)[..., None]
    lin = _srgb_to_lin(photo)
    skin = np.median(lin[mask[..., 0] > 0.9], axis=0)
    target = monk_albedo(level) * (skin.mean() / monk_albedo(6).mean())
    return _lin_to_srgb(lin * (1 - mask + mask * target / skin))


# A real face re-toned across the Monk scale: BlazeFace + FaceMesh must not depend on skin tone. (The
# synthetic stability subjects are harder: their renders have no eyeballs, and at MST 9-10 BlazeFace
# misses some even undegraded; see docs/perception.md. On the re-toned astronaut every level is found,
# also in grayscale and 20x underexposed; only MST 10 at JPEG quality 5 is missed.)
@pytest.mark.parametrize("level", [1, 4, 8, 10])
@pytest.mark.parametrize("variant", ["colour", "grayscale", "underexposed"])
def test_detects_every_skin_tone(reference, astronaut, models_root, level, variant):
    img = _retone(astronaut, reference, level)
    if variant == "grayscale":
        img = np.repeat(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)[..., None], 3, axis=2)
    elif variant == "underexposed":
        img = _lin_to_srgb(_srgb_to_lin(img) * 0.05)
    x, y = reference.face.landmarks.points[50, :2].astype(int)  # the right cheek: the re-toning reached it
    cheek = _srgb_to_lin(img[y - 3 : y + 4, x - 3 : x + 4]).mean() / (0.05 if variant == "underexposed" else 1)
    before = _srgb_to_lin(astronaut[y - 3 : y + 4, x - 3 : x + 4]).mean()
    assert cheek > 1.2 * before if level < 6 else cheek < 0.5 * before  # the photo's skin counts as MST 6
    det = detect(img, S, models_root)
    assert _mean_err(det.face.landmarks.points[:, :2], reference.face.landmarks.points[:, :2]) < 0.03 * _face_size(reference)


def test_small_face_in_large_photo(astronaut, models_root):
    """A 40-pixel face in a 12-megapixel photo is found by the tiled full-range pass."""
    from skimage import data

    canvas = cv2.resize(data.coffee(), (4000, 3000))  # a real background with face-like false alarms
    k = 40 / 96
    small = cv2.resize(astronaut, None, fx=k, fy=k, interpolation=cv2.INTER_AREA)
    canvas[1200 : 1200 + small.shape[0], 2500 : 2500 + small.shape[1]] = small
    det = detect(canvas, S, models_root)
    b = det.face.detection.box
    assert 2540 < b[0] < 2600 and 1200 < b[1] < 1260 and 30 < b[2] - b[0] < 55


def test_face_filling_the_frame(astronaut, models_root):
    img = cv2.resize(astronaut[70:190, 165:285], (1400, 1400), interpolation=cv2.INTER_CUBIC)
    det = detect(img, S, models_root)
    assert det.face.landmarks.presence > 0.9
    pts = det.face.landmarks.points
    assert pts[:, 0].min() > -100 and pts[:, 0].max() < 1500


def test_no_face(models_root):
    from skimage import data

    det = detect(np.ascontiguousarray(data.coffee()), S, models_root)
    assert det.chosen is None and det.faces == ()
    from fitme_cli.errors import NoFaceFound

    with pytest.raises(NoFaceFound):
        det.face


def test_grayscale_photo_as_rgb(reference, astronaut, models_root):
    gray = cv2.cvtColor(astronaut, cv2.COLOR_RGB2GRAY)
    det = detect(np.repeat(gray[..., None], 3, axis=2), S, models_root)
    assert _mean_err(det.face.landmarks.points[:, :2], reference.face.landmarks.points[:, :2]) < 0.03 * _face_size(reference)


def test_bad_image_argument(models_root):
    with pytest.raises(ValueError, match=r"expected an \(H, W, 3\) uint8 RGB image, got ndarray \(4, 4\) float64"):
        detect_faces(np.zeros((4, 4)), S, models_root)


def test_settings_are_checked():
    with pytest.raises(ValueError, match="min_face_px must be >= 8, got 2"):
        DetectSettings(min_face_px=2)


def test_json_round_trip(reference):
    import json

    doc = json.loads(json.dumps(reference.to_json()))
    assert doc["chosen"] == 0 and len(doc["faces"][0]["landmarks"]) == 468 and len(doc["faces"][0]["ibug68"]) == 68
    assert set(doc["faces"][0]["pose"]) == {"yaw", "pitch", "roll"}


def test_several_faces(astronaut, models_root):
    """Two people side by side: both found; landmarks for the largest only, or for all with all_faces."""
    import cv2

    from fitme_cli.io import sample_photo

    hopper = cv2.resize(sample_photo("grace_hopper").rgb, (400, 469))  # her face ~160 px, the astronaut's 96
    canvas = np.zeros((512, 912, 3), np.uint8)
    canvas[:, :512] = astronaut
    canvas[:469, 512:] = hopper
    det = detect(canvas, S, models_root)
    assert len(det.faces) == 2 and det.chosen == 0
    assert det.faces[0].detection.box[0] > 512  # the larger face, Grace Hopper's, comes first
    assert det.faces[0].landmarks is not None and det.faces[1].landmarks is None
    both = detect(canvas, DetectSettings(identity=False, all_faces=True), models_root)
    assert all(f.landmarks is not None for f in both.faces)
    assert both.faces[1].detection.box[2] < 512
