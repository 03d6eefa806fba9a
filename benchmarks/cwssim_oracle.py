"""Reproduce the oracle numbers of tests/test_metrics_cwssim.py: CW-SSIM of d2turb.eval.cwssim beside IQA-PyTorch's
(pyiqa 0.1.16, ``archs/ssim_arch.py`` CW_SSIM) and the coarsest pyramid level beside pyrtools'.

pyiqa cannot be installed next to this project (it pins a newer torch and pulls ~60 packages), so its source is
unpacked from the wheel without its dependencies and its CW-SSIM module imported without the package's heavy
``__init__``; pyrtools installs without dependencies into a scratch folder::

    pip download --no-deps pyiqa==0.1.16 pyrtools==1.1.1 -d /tmp/oracle
    python -m zipfile -e /tmp/oracle/pyiqa-0.1.16-py3-none-any.whl /tmp/oracle/pyiqa_src
    pip install --no-deps --target /tmp/oracle/site /tmp/oracle/pyrtools-1.1.1-*.whl
    PYTHONPATH=src:/tmp/oracle/site python benchmarks/cwssim_oracle.py --pyiqa /tmp/oracle/pyiqa_src/pyiqa
"""

from __future__ import annotations

import argparse
import sys
import types

import numpy as np
import torch
from scipy import ndimage
from skimage import data

from d2turb.eval.cwssim import coarsest_bands, cw_ssim


def _pyiqa_cw_ssim(root: str):
    for name, path in (("pyiqa", root), ("pyiqa.utils", f"{root}/utils"), ("pyiqa.archs", f"{root}/archs")):
        module = types.ModuleType(name)
        module.__path__ = [path]
        sys.modules[name] = module
    from pyiqa.archs.ssim_arch import CW_SSIM

    metric = CW_SSIM()

    def score(a: np.ndarray, b: np.ndarray) -> float:
        def t(x):
            return torch.from_numpy(x)[None, None].repeat(1, 3, 1, 1) if x.ndim == 2 else torch.from_numpy(x)[None]

        return float(metric(t(a), t(b)))

    return score


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pyiqa", required=True, help="the unpacked pyiqa package folder")
    args = parser.parse_args()
    pyiqa = _pyiqa_cw_ssim(args.pyiqa)
    cam = data.camera().astype(np.float64) / 255
    odd = cam[100:303, 50:307]
    ast = data.astronaut().astype(np.float64).transpose(2, 0, 1) / 255
    cases = {
        "transposed": (cam, cam.T.copy()),
        "odd_shift": (odd, ndimage.shift(odd, (2, -3), order=1, mode="nearest")),
        "astronaut_blur": (ast, ndimage.gaussian_filter(ast, (0, 3, 3))),
        "shift 1 px": (cam, np.roll(cam, 1, axis=1)),
    }
    for name, (a, b) in cases.items():
        ours, ref = cw_ssim(a, b), pyiqa(a, b)
        print(f"{name}: d2turb {ours:.6f}  pyiqa {ref:.6f}  |Δ| {abs(ours - ref):.1e}")
    try:
        import pyrtools
    except ImportError:
        print("pyrtools not importable: pyramid check skipped")
        return
    pyr = pyrtools.pyramids.SteerablePyramidFreq(cam, height=4, order=7, is_complex=True)
    worst = max(
        float(np.abs(band - pyr.pyr_coeffs[(3, b)]).max() / np.abs(pyr.pyr_coeffs[(3, b)]).max())
        for b, band in enumerate(coarsest_bands(cam))
    )
    print(f"coarsest level vs pyrtools: largest relative difference {worst:.1e}")


if __name__ == "__main__":
    main()
