"""The public API (d2turb/__init__.py, docs/api.md): the names a user needs come from ``from d2turb import …``,
lazily, each documented in kornia's form; every code block of docs/api.md runs as it stands."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

import d2turb

ROOT = Path(__file__).resolve().parents[1]
PUBLIC = ["Simulator", "TurbulenceParams", "Restorer", "ClipRestorer", "measure_clip", "BlindDeblur", "PhysicsDeblur"]


def test_import_d2turb_imports_no_torch():
    code = "import sys, d2turb; assert 'torch' not in sys.modules, 'torch'; print(sorted(d2turb.__all__))"
    env_path = str(ROOT / "src")
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env={"PYTHONPATH": env_path}, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert set(PUBLIC) <= set(eval(proc.stdout))


@pytest.mark.parametrize("name", PUBLIC)
def test_public_names_are_importable_from_the_top(name):
    obj = getattr(d2turb, name)
    assert obj.__name__ == name and name in dir(d2turb)
    doc = obj.__doc__ or ""
    assert "Args:" in doc or "Args:" in (getattr(obj, "__init__", None).__doc__ or ""), f"{name}: no Args section"


@pytest.mark.slow
def test_api_md_lists_every_public_name_and_its_examples_run(capsys):
    text = (ROOT / "docs" / "api.md").read_text()
    for name in PUBLIC:
        assert f"`{name}`" in text, name
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) >= 4
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, "docs/api.md", "exec"), namespace)  # one namespace: later blocks use earlier names
    printed = capsys.readouterr().out
    assert "torch.Size([1, 3, 64, 64])" in printed
    assert namespace["restored"][0].shape == namespace["clean"].shape[1:]
    assert namespace["result"]["dr0"] > 0


MODULES = [
    "d2turb.sim.simulator",
    "d2turb.sim.params",
    "d2turb.sim.optics",
    "d2turb.restore.single",
    "d2turb.clip.deblur",
]


@pytest.mark.parametrize("module", MODULES)
def test_docstring_examples_run(module):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0
