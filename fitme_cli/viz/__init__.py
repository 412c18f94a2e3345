"""Pictures for people: overlays, contact sheets."""

from .detection_overlay import draw_detection

__all__ = ["draw_detection"]
