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


@pytest.fixture(scope="module")
def one_thread():
    """torch on one thread for a test module: small tensors run faster, and a concurrent job on the
    2 cores does not make OpenMP threads spin against each other."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
