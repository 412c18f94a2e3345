"""Photo input and file output."""

from .atomic import atomic_write_bytes, atomic_write_image
from .images import ImageSettings, LoadedImage, load_image

__all__ = ["ImageSettings", "LoadedImage", "load_image", "atomic_write_bytes", "atomic_write_image"]
