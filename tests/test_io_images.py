"""Photo loading: every bad input gets its own error and a message naming the problem; odd formats
load with the right colours; EXIF orientation is applied."""

import io
import os
import time

import numpy as np
import pytest
from PIL import Image

from fitme_cli import errors
from fitme_cli.io import ImageSettings, atomic_write_image, load_image


@pytest.fixture(scope="module")
def rgb(astronaut):
    return np.ascontiguousarray(astronaut[100:228, 150:310])  # 160x128, a face, real colours


def _save(img: Image.Image, path, **kw):
    img.save(path, **kw)
    return path


def test_missing(tmp_path):
    with pytest.raises(errors.InputNotFound, match="file not found"):
        load_image(tmp_path / "nope.jpg")


def test_directory(tmp_path):
    with pytest.raises(errors.InputIsDirectory, match="is a directory"):
        load_image(tmp_path)


def test_empty(tmp_path):
    (tmp_path / "e.jpg").write_bytes(b"")
    with pytest.raises(errors.InputEmpty, match="0 bytes"):
        load_image(tmp_path / "e.jpg")


@pytest.mark.parametrize("content", [b"hello, not an image\n", bytes(range(256)) * 10, b"\xff\xd8\xff\xe0garbage"])
def test_not_an_image(tmp_path, content):
    (tmp_path / "x.jpg").write_bytes(content)
    with pytest.raises((errors.NotAnImage, errors.TruncatedImage)) as e:
        load_image(tmp_path / "x.jpg")
    assert str(tmp_path / "x.jpg") in str(e.value)


@pytest.mark.parametrize("fmt,frac", [("JPEG", 0.5), ("JPEG", 0.97), ("PNG", 0.5), ("PNG", 0.97)])
def test_truncated(tmp_path, rgb, fmt, frac):
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, fmt)
    data = buf.getvalue()
    p = tmp_path / f"t.{fmt.lower()}"
    p.write_bytes(data[: int(len(data) * frac)])
    with pytest.raises(errors.TruncatedImage, match="truncated"):
        load_image(p)


def _png_header_claiming(w: int, h: int) -> bytes:
    """A valid 1x1 PNG whose IHDR is rewritten to claim w x h (CRC fixed): a decompression bomb's header."""
    import struct
    import zlib

    buf = io.BytesIO()
    Image.new("RGB", (1, 1)).save(buf, "PNG")
    data = bytearray(buf.getvalue())
    ihdr = 8  # after the signature: length(4) type(4) data(13) crc(4)
    data[ihdr + 8 : ihdr + 16] = struct.pack(">II", w, h)
    data[ihdr + 21 : ihdr + 25] = struct.pack(">I", zlib.crc32(bytes(data[ihdr + 4 : ihdr + 21])))
    return bytes(data)


def test_decompression_bomb_is_refused_before_decoding(tmp_path):
    p = tmp_path / "bomb.png"
    p.write_bytes(_png_header_claiming(100_000, 100_000))
    t0 = time.perf_counter()
    with pytest.raises(errors.ImageTooLarge, match=r"100000x100000 = 10000 megapixels; the limit is 100"):
        load_image(p)
    assert time.perf_counter() - t0 < 0.5


def test_file_size_limit(tmp_path, rgb):
    p = _save(Image.fromarray(rgb), tmp_path / "a.png")
    with pytest.raises(errors.ImageTooLarge, match="MiB"):
        load_image(p, ImageSettings(max_file_bytes=100))


def test_permission_denied(tmp_path, rgb, monkeypatch):
    from fitme_cli.io import images

    p = _save(Image.fromarray(rgb), tmp_path / "a.png")
    p.chmod(0)
    if os.geteuid() == 0:  # root reads any file: make the check see what a user would
        monkeypatch.setattr(images.os, "access", lambda path, mode: False)
    with pytest.raises(errors.InputNotReadable, match="permission denied"):
        load_image(p)


def test_rgb_png_round_trip(tmp_path, rgb):
    im = load_image(_save(Image.fromarray(rgb), tmp_path / "a.png"))
    assert im.rgb.dtype == np.uint8 and im.rgb.shape == rgb.shape and np.array_equal(im.rgb, rgb)
    assert im.original_mode == "RGB" and im.exif_orientation == 1 and im.focal_length_35mm is None


def test_16bit_rgb_png(tmp_path, rgb):
    import cv2

    p = tmp_path / "a16.png"
    cv2.imwrite(str(p), (rgb.astype(np.uint16) * 257)[..., ::-1])
    assert np.abs(load_image(p).rgb.astype(int) - rgb).max() <= 1


def test_16bit_gray_png(tmp_path, rgb):
    gray = np.asarray(Image.fromarray(rgb).convert("L"))
    p = _save(Image.fromarray(gray.astype(np.uint16) * 257), tmp_path / "g16.png")
    im = load_image(p)
    assert im.original_mode.startswith("I")
    assert np.abs(im.rgb.astype(int) - gray[..., None]).max() <= 1 and im.rgb.shape == rgb.shape


def test_cmyk_jpeg_colours(tmp_path, rgb):
    p = _save(Image.fromarray(rgb).convert("CMYK"), tmp_path / "c.jpg", quality=95)
    im = load_image(p)
    assert im.original_mode == "CMYK"
    assert np.abs(im.rgb.astype(float) - rgb).mean() < 6


@pytest.mark.parametrize("mode", ["L", "P", "1", "LA"])
def test_other_modes(tmp_path, rgb, mode):
    src = Image.fromarray(rgb).convert(mode)
    im = load_image(_save(src, tmp_path / "m.png"))
    assert im.rgb.shape == rgb.shape and im.rgb.dtype == np.uint8
    assert np.abs(im.rgb.astype(float) - np.asarray(src.convert("RGB"), float)).mean() < 1


def test_rgba_composited_over_white(tmp_path, rgb):
    a = np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])
    a[:10, :10, 3] = 0
    im = load_image(_save(Image.fromarray(a, "RGBA"), tmp_path / "a.png"))
    assert np.all(im.rgb[:10, :10] == 255) and np.array_equal(im.rgb[20:, 20:], rgb[20:, 20:])


@pytest.mark.parametrize("fmt,ext,tol", [("TIFF", "tif", 0), ("BMP", "bmp", 0), ("WEBP", "webp", 8)])
def test_other_formats(tmp_path, rgb, fmt, ext, tol):
    im = load_image(_save(Image.fromarray(rgb), tmp_path / f"a.{ext}", format=fmt, **({"quality": 95} if fmt == "WEBP" else {})))
    assert np.abs(im.rgb.astype(float) - rgb).mean() <= max(tol, 0.0)


# For each EXIF orientation: how to turn the upright image into the stored one.
_STORE = {
    1: lambda a: a,
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: np.swapaxes(a, 0, 1),
    6: lambda a: np.rot90(a, 1),
    7: lambda a: np.swapaxes(a[::-1, ::-1], 0, 1),
    8: lambda a: np.rot90(a, -1),
}


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation(tmp_path, rgb, orientation):
    stored = np.ascontiguousarray(_STORE[orientation](rgb))
    exif = Image.Exif()
    exif[0x0112] = orientation
    p = _save(Image.fromarray(stored), tmp_path / "o.png", exif=exif.tobytes())
    im = load_image(p)
    assert im.exif_orientation == orientation
    assert np.array_equal(im.rgb, rgb), f"orientation {orientation} not undone"


def test_focal_length_from_exif(tmp_path, rgb):
    exif = Image.Exif()
    ifd = exif.get_ifd(0x8769)
    ifd[0xA405] = 26
    p = _save(Image.fromarray(rgb), tmp_path / "f.jpg", exif=exif.tobytes())
    assert load_image(p).focal_length_35mm == 26.0


def test_atomic_write_image(tmp_path, rgb):
    p = tmp_path / "sub" / "o.png"
    atomic_write_image(p, rgb)
    assert np.array_equal(load_image(p).rgb, rgb)
    assert [f.name for f in p.parent.iterdir()] == ["o.png"]  # no temporary left behind
    mask = os.umask(0)
    os.umask(mask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~mask  # not mkstemp's 0600
    with pytest.raises(errors.OutputNotWritable, match="unsupported image type"):
        atomic_write_image(tmp_path / "o.gif", rgb)
    (tmp_path / "file").write_text("x")
    with pytest.raises(errors.OutputNotWritable):
        atomic_write_image(tmp_path / "file" / "o.png", rgb)
    with pytest.raises(ValueError, match=r"expected an \(H, W, 3\) uint8 RGB image"):
        atomic_write_image(p, rgb.astype(np.float32))
