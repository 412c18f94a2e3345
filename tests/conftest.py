import numpy as np
import pytest


@pytest.fixture(scope="session")
def models_root():
    """The models directory with every converted network (built on first use, as in production)."""
    from fitme_cli.perception.registry import ensure_models

    return ensure_models(["blazeface_short", "blazeface_full", "facemesh"])


@pytest.fixture(scope="session")
def astronaut() -> np.ndarray:
    """A real photo shipped inside scikit-image: (512, 512, 3) uint8 RGB, one upright frontal face."""
    from skimage import data

    return data.astronaut()
