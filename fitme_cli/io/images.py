"""Load a photo the way every command needs it: upright, 8-bit sRGB RGB, with a clear error for bad input.

Checks run cheapest first and before any pixel is decoded: the path, the file size, the header's
dimensions (decompression-bomb guard), then a full decode that must not be truncated.
"""

from __future__ import annotations

import io
import os
import warnings
from dataclasses import dataclass
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
)

__all__ = ["ImageSettings", "LoadedImage", "load_image"]

_EXIF_IFD = 0x8769
_FOCAL_35MM, _FOCAL, _FP_XRES, _FP_UNIT = 0xA405, 0x920A, 0xA20E, 0xA210
_ORIENTATION = 0x0112


@dataclass(frozen=True)
class ImageSettings:
    max_pixels: int = 100_000_000  # larger headers are refused before decoding
    max_file_bytes: int = 200 * 1024 * 1024

    def __post_init__(self) -> None:
        if self.max_pixels <= 0 or self.max_file_bytes <= 0:
            raise ValueError(f"limits must be positive, got {self.max_pixels} pixels, {self.max_file_bytes} bytes")


@dataclass(frozen=True)
class LoadedImage:
    rgb: np.ndarray  # (H, W, 3) uint8 sRGB, EXIF orientation applied, alpha composited over white
    path: Path
    original_mode: str  # PIL mode as stored: 'RGB', 'I;16', 'CMYK', 'L', 'RGBA', 'P', ...
    original_size: tuple[int, int]  # (width, height) as stored, before orientation
    exif_orientation: int  # 1 (upright) to 8
    focal_length_35mm: float | None  # 35 mm-equivalent focal length from EXIF, mm; None if unknown

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])


def _register_heif() -> None:
    try:  # optional: HEIC from iPhones, only if the user installed pillow-heif
        from pillow_heif import register_heif_opener

        register_heif_opener()
    except ImportError:
        pass


def _focal_35mm(exif, width: int) -> float | None:
    """FocalLengthIn35mmFilm, else FocalLength x 36 mm / sensor width from the focal-plane resolution."""
    try:
        ifd = exif.get_ifd(_EXIF_IFD)
    except Exception:  # malformed EXIF must not fail the photo
        return None
    f35 = ifd.get(_FOCAL_35MM)
    if f35:
        return float(f35)
    f, xres, unit = ifd.get(_FOCAL), ifd.get(_FP_XRES), ifd.get(_FP_UNIT, 2)
    unit_mm = {2: 25.4, 3: 10.0, 4: 1.0}.get(int(unit) if unit else 2)
    try:
        if f and xres and unit_mm and float(xres) > 0:
            sensor_mm = width / float(xres) * unit_mm
            if sensor_mm > 0:
                return float(f) * 36.0 / sensor_mm
    except (TypeError, ValueError, ZeroDivisionError):
        pass
    return None


def _to_rgb8(img) -> np.ndarray:
    """Any PIL mode -> (H, W, 3) uint8."""
    from PIL import Image

    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        a = np.asarray(img).astype(np.float64)
        top = 65535.0 if mode.startswith("I;16") or a.max() > 255 else 255.0
        g = np.clip(np.round(a * (255.0 / top)), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    if mode == "F":
        a = np.asarray(img, np.float64)
        g = np.clip(np.round(a * 255.0 if a.max() <= 1.0 else a), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in img.info):
        rgba = img.convert("RGBA")
        white = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
        return np.asarray(Image.alpha_composite(white, rgba).convert("RGB"))
    if mode == "CMYK" and img.info.get("icc_profile"):
        try:
            from PIL import ImageCms

            src = ImageCms.ImageCmsProfile(io.BytesIO(img.info["icc_profile"]))
            return np.asarray(ImageCms.profileToProfile(img, src, ImageCms.createProfile("sRGB"), outputMode="RGB"))
        except Exception:  # a broken profile falls back to the plain conversion
            pass
    return np.asarray(img.convert("RGB"))


def load_image(path: str | Path, settings: ImageSettings = ImageSettings()) -> LoadedImage:
    """Load ``path`` as an upright 8-bit RGB photo, or raise a FitmeError that names the problem."""
    from PIL import Image, ImageFile, ImageOps, UnidentifiedImageError

    path = Path(path)
    if not path.exists():
        raise InputNotFound("file not found", path)
    if path.is_dir():
        raise InputIsDirectory("is a directory; expected an image file", path)
    size = path.stat().st_size
    if size == 0:
        raise InputEmpty("file is empty (0 bytes)", path)
    if size > settings.max_file_bytes:
        raise ImageTooLarge(f"file is {size / 2**20:.0f} MiB; the limit is {settings.max_file_bytes / 2**20:.0f} MiB", path)
    if not os.access(path, os.R_OK):
        raise InputNotReadable("permission denied", path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputNotReadable(f"cannot read: {e.strerror or e}", path) from None

    _register_heif()
    ImageFile.LOAD_TRUNCATED_IMAGES = False  # a half-grey photo must never pass as a photo
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        old_limit = Image.MAX_IMAGE_PIXELS
        Image.MAX_IMAGE_PIXELS = None  # our own limit below, checked on the header
        try:
            img = Image.open(io.BytesIO(data))
        except UnidentifiedImageError:
            raise NotAnImage("not an image (unrecognised format)", path) from None
        except (OSError, SyntaxError, ValueError) as e:
            raise NotAnImage(f"not a readable image: {e}", path) from None
        finally:
            Image.MAX_IMAGE_PIXELS = old_limit
        w, h = img.size
        if w <= 0 or h <= 0:
            raise NotAnImage(f"image has no pixels ({w}x{h})", path)
        if w * h > settings.max_pixels:
            raise ImageTooLarge(
                f"image is {w}x{h} = {w * h / 1e6:.0f} megapixels; the limit is {settings.max_pixels / 1e6:.0f}", path
            )
        original_mode = img.mode
        try:
            img.load()  # with LOAD_TRUNCATED_IMAGES off, Pillow raises on a JPEG or PNG cut anywhere
        except (OSError, SyntaxError, ValueError, EOFError) as e:
            raise TruncatedImage(f"image data is truncated or corrupt ({e})", path) from None
        try:
            exif = img.getexif()
        except Exception:
            exif = {}
        orientation = int(exif.get(_ORIENTATION, 1) or 1) if hasattr(exif, "get") else 1
        focal = _focal_35mm(exif, w) if hasattr(exif, "get_ifd") else None
        try:
            upright = ImageOps.exif_transpose(img)
        except Exception:  # bad orientation tag: keep as stored
            upright, orientation = img, 1
        rgb = np.ascontiguousarray(_to_rgb8(upright))
    return LoadedImage(rgb, path, original_mode, (w, h), orientation if 1 <= orientation <= 8 else 1, focal)
