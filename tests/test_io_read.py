"""d2turb.io.read: float TIFF images are read as they are, or refused when out of range or non-finite."""

from pathlib import Path

import numpy as np
import pytest
import torch
from hostile_input import one_error_line, run_cli
from PIL import Image


def _float_tiff(path: Path, values: np.ndarray) -> Path:
    Image.fromarray(values.astype(np.float32), mode="F").save(path)
    return path


@pytest.mark.parametrize(
    "name, words",
    [("scale", ["0 to 1000", "[0, 1]"]), ("inf", ["NaN or infinite"]), ("nan", ["NaN or infinite"])],
)
def test_float_tiff_out_of_range_or_non_finite_is_refused(name, words, tmp_path, capsys):
    values = np.linspace(0, 1, 24 * 32).reshape(24, 32)
    if name == "scale":
        values = values * 1000
    else:
        values[3, 4] = np.inf if name == "inf" else np.nan
    image = _float_tiff(tmp_path / f"{name}.tif", values)
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o")])
    assert rc == 2
    one_error_line(err, f"{name}.tif", *words)
    assert not (tmp_path / "o").exists()


def test_float_tiff_in_range_is_read_as_is(tmp_path):
    from d2turb.io import read_image

    values = np.linspace(0, 1, 24 * 32).reshape(24, 32).astype(np.float32)
    image = read_image(_float_tiff(tmp_path / "ok.tif", values))
    assert image.shape == (3, 24, 32) and torch.equal(image[1], torch.from_numpy(values))
