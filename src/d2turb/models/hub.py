"""Where weights are found: a weights argument (a path, a name, or ``input`` for the identity) → a file, by the
search path ($D2TURB_WEIGHTS_DIR, the cache, the weights shipped in the package), and the recommended shipped model.
Reading and writing the files: :mod:`d2turb.models.weights`."""

from __future__ import annotations

import os
import re
from importlib import resources
from pathlib import Path

from d2turb.errors import D2TurbError
from d2turb.io import cache_dir
from d2turb.models.weights import WEIGHTS_SUFFIX

IDENTITY_NAME = "input"  # the identity baseline: restore returns its input


_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


# The shipped weights recommended for single-frame restoration: the default of `d2turb restore`, Restorer(), the demo
# and the page (MODEL_CARD.md). Shipped weights are the package's resources/weights/NAME.safetensors.
RECOMMENDED_WEIGHTS = "nafnet-gpu-spectral3"
# shipped weights no longer in the package, and why: a name here is refused with that reason (unless a file of that
# name is found on the search path, e.g. a copy the user kept)
RETIRED_WEIGHTS = {
    "nafnet-gpu-spectral": "an intermediate stage of nafnet-gpu-spectral3 (the GPU leases' checkout, weights included, "
    "must stay under 64 MiB); use nafnet-gpu-spectral3 or nafnet-gpu-spectral2",
}


def shipped_weights_dir() -> Path:
    """The package's ``resources/weights``: the weights shipped with d2turb."""
    return Path(str(resources.files("d2turb"))) / "resources" / "weights"


def shipped_weights() -> list[str]:
    """Names of the weights shipped in the package (``resources/weights/NAME.safetensors``), the recommended one
    (:data:`RECOMMENDED_WEIGHTS`) first, then the others in name order."""
    folder = shipped_weights_dir()
    files = folder.glob(f"*{WEIGHTS_SUFFIX}") if folder.is_dir() else []
    names = sorted(f.stem for f in files if _NAME_RE.match(f.stem))
    return sorted(names, key=lambda n: n != RECOMMENDED_WEIGHTS)


def recommended_weights() -> Path:
    """The file of the recommended shipped weights (:data:`RECOMMENDED_WEIGHTS` in the package's resources/weights,
    never a same-named file elsewhere): what restoration uses when no weights are given.

    Raises:
        D2TurbError: it is not shipped with this installation.
    """
    path = shipped_weights_dir() / f"{RECOMMENDED_WEIGHTS}{WEIGHTS_SUFFIX}"
    if not path.is_file():
        raise D2TurbError(
            f"no restoration model is shipped with this installation ({path.name} not in {path.parent}); "
            f"pass --weights (a .safetensors file or a weights name), or 'input' for the identity baseline"
        )
    return path


def weights_search_path(name: str) -> list[Path]:
    """Where a weights *name* is looked for, in order: each folder of $D2TURB_WEIGHTS_DIR (os.pathsep
    separated), $D2TURB_CACHE_DIR/weights (default ~/.cache/d2turb/weights), then the package's resources/weights."""
    folders = [Path(p).expanduser() for p in os.environ.get("D2TURB_WEIGHTS_DIR", "").split(os.pathsep) if p]
    folders.append(cache_dir("weights"))
    folders.append(shipped_weights_dir())
    return [folder / f"{name}{WEIGHTS_SUFFIX}" for folder in folders]


def resolve_weights(weights: str | os.PathLike) -> Path | str:
    """A weights argument → an existing .safetensors path, or the identity name "input"."""
    text = os.fspath(weights)
    if text == IDENTITY_NAME:
        return IDENTITY_NAME
    path = Path(text).expanduser()
    weight_suffixes = (WEIGHTS_SUFFIX, ".pt", ".pth", ".ckpt", ".bin")
    looks_like_path = path.suffix.lower() in weight_suffixes or "/" in text or os.sep in text or path.exists()
    if looks_like_path:
        if path.suffix.lower() in weight_suffixes[1:]:
            raise D2TurbError(
                f"{path}: only {WEIGHTS_SUFFIX} weights written by save_pretrained are supported; convert a "
                f"checkpoint with: d2turb convert {path} {path.with_suffix(WEIGHTS_SUFFIX)} [--model NAME]"
            )
        if not path.is_file():
            raise D2TurbError(f"{path}: weights file not found")
        return path
    if not _NAME_RE.match(text):
        raise D2TurbError(f"invalid weights name {text!r}: use a {WEIGHTS_SUFFIX} path or a name like 'd2turb-nafnet'")
    candidates = weights_search_path(text)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    if text in RETIRED_WEIGHTS:
        raise D2TurbError(f"weights {text!r} no longer ship with d2turb: {RETIRED_WEIGHTS[text]}")
    looked = ", ".join(str(c) for c in candidates)
    raise D2TurbError(f"weights {text!r} not found; looked in: {looked} (set D2TURB_WEIGHTS_DIR or pass a path)")
