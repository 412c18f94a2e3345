"""Domain errors. Each carries a distinct process exit code; the CLI prints one line, never a traceback."""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "FitmeError",
    "InputNotFound",
    "InputIsDirectory",
    "InputEmpty",
    "NotAnImage",
    "TruncatedImage",
    "ImageTooLarge",
    "NoFaceFound",
    "OutputNotWritable",
    "InputNotReadable",
    "UnsupportedImage",
    "ModelMissing",
    "ModelBuildError",
    "WrongLayout",
    "AvatarInvalid",
    "DifferentPeople",
    "DeviceUnavailable",
    "ModelMismatch",
]


class FitmeError(Exception):
    """Base class. ``exit_code`` is the CLI's exit status for this error; ``path`` the file concerned."""

    exit_code = 1

    def __init__(self, message: str, path: str | Path | None = None):
        super().__init__(message)
        self.path = None if path is None else Path(path)
        self.message = message

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path is not None else self.message


class InputNotFound(FitmeError):
    exit_code = 10


class InputIsDirectory(FitmeError):
    exit_code = 11


class InputEmpty(FitmeError):
    exit_code = 12


class NotAnImage(FitmeError):
    exit_code = 13


class TruncatedImage(FitmeError):
    exit_code = 14


class ImageTooLarge(FitmeError):
    exit_code = 15


class NoFaceFound(FitmeError):
    exit_code = 16


class OutputNotWritable(FitmeError):
    exit_code = 17


class InputNotReadable(FitmeError):
    exit_code = 18


class UnsupportedImage(FitmeError):
    """A real image in a format or layout this build cannot decode (e.g. HEIC without pillow-heif)."""

    exit_code = 19


class ModelMissing(FitmeError):
    exit_code = 20


class ModelBuildError(FitmeError):
    exit_code = 21


class WrongLayout(FitmeError):
    """An image that is not a map in fitme's UV layout (e.g. a photo given to `fitme augment`)."""

    exit_code = 22


class AvatarInvalid(FitmeError):
    """A directory that is not a readable avatar (missing files, another schema, inconsistent params)."""

    exit_code = 23


class DifferentPeople(FitmeError):
    """Photos given to one fit whose identity descriptors disagree."""

    exit_code = 24


class DeviceUnavailable(FitmeError):
    """--device names a device this torch build or machine does not have."""

    exit_code = 25


class ModelMismatch(AvatarInvalid):
    """An avatar whose parameters mean another face under the models now in ``models/`` (a rebuilt shape
    model, another generator): reading it on would silently give a different head."""

    exit_code = 26
