import os
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(
    os.environ.get("D2TURB_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
).resolve()


@pytest.fixture(autouse=True)
def _torch_threads():
    torch.set_num_threads(2)


@pytest.fixture
def shared_data() -> Path:
    """../shared/data (real images); tests that need it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture
def astronaut() -> torch.Tensor:
    """A built-in natural RGB sample image (1, 3, 256, 256) in [0, 1]."""
    from skimage import data, transform

    img = transform.resize(data.astronaut(), (256, 256), anti_aliasing=True)
    return torch.from_numpy(img).float().permute(2, 0, 1)[None].contiguous()
