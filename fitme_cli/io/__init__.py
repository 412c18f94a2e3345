"""Photo input and file output."""

from .atomic import atomic_write_bytes, atomic_write_image
from .images import (
    PHOTO_FORMATS,
    SAMPLE_PHOTOS,
    ImageSettings,
    LoadedImage,
    SamplePhoto,
    apply_exif_orientation,
    available_samples,
    load_image,
    sample_photo,
    write_sample_photo,
)

__all__ = [
    "ImageSettings",
    "LoadedImage",
    "load_image",
    "apply_exif_orientation",
    "PHOTO_FORMATS",
    "SamplePhoto",
    "SAMPLE_PHOTOS",
    "available_samples",
    "sample_photo",
    "write_sample_photo",
    "atomic_write_bytes",
    "atomic_write_image",
]
