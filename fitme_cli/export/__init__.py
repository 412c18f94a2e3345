"""``fitme export`` and ``fitme render``: the avatar as glTF/GLB/OBJ with full-head maps, and relit contact
sheets (docs/export.md). One concept per module: ``source`` (what is read from an avatar), ``mesh``
(closed head, seams, tangents, morph targets), ``maps`` (fill, seam, upsample, encode), ``material``
(Blinn-Phong -> PBR), ``gltf`` / ``obj`` (writers), ``pipeline`` (the command as a function),
``render`` (relighting presets and the sheet), ``validate`` (the Khronos glTF-Validator through node)."""

from .pipeline import ExportResult, ExportSettings, export_avatar

__all__ = ["ExportSettings", "ExportResult", "export_avatar"]
