"""fitme: photos of a face to a relightable 3D avatar (FitMe, CVPR 2023)."""

__version__ = "0.1.0"

__all__ = ["__version__"]
