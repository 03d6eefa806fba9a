"""Weights files (d2turb.models): an impossible header, a tensor of the wrong dtype or an impossible config
is one line naming the file, on loading and on converting."""

import json
from pathlib import Path

import pytest
import torch
from hostile_input import TINY_NAFNET, one_error_line, rgb, run_cli

from d2turb.cli import main


@pytest.fixture
def nafnet_file(tmp_path) -> Path:
    from d2turb.models import create_model, save_pretrained

    torch.manual_seed(0)
    return save_pretrained(create_model("nafnet", **TINY_NAFNET), tmp_path / "w.safetensors")


def _rewrite_metadata(path: Path, dest: Path, **changes) -> Path:
    """The same tensors (so the same checksum) under changed metadata, written with safetensors itself."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), framework="pt") as f:
        metadata = {**f.metadata(), **changes}
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    save_file(tensors, str(dest), metadata=metadata)
    return dest


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"d2turb_format": "3"}, ["format '3'"]),
        ({"d2turb_config": json.dumps({"name": "nosuch", **TINY_NAFNET})}, ["unknown model 'nosuch'"]),
        ({"d2turb_config": json.dumps({"name": "nafnet", **TINY_NAFNET, "width": -2})}, ["nafnet", "-2"]),
        (
            {
                "d2turb_config": json.dumps(
                    {"name": "nafnet", "width": 8, "enc_blocks": [1] * 64, "dec_blocks": [1] * 64}
                )
            },
            ["nafnet", "bad config"],
        ),
    ],
)
def test_weights_with_an_impossible_header_are_one_line_naming_the_file(changes, words, nafnet_file, tmp_path, capsys):
    bad = _rewrite_metadata(nafnet_file, tmp_path / "bad.safetensors", **changes)
    image = rgb(tmp_path / "in" / "a.png", 24, 32)
    rc, _, err = run_cli(capsys, ["restore", str(image), "--weights", str(bad), "--out", str(tmp_path / "o")])
    assert rc == 2
    one_error_line(err, str(bad), *words)


def test_weights_of_the_wrong_dtype_are_refused(tmp_path, capsys):
    from d2turb.models import create_model

    state = create_model("nafnet", **TINY_NAFNET).state_dict()
    name = next(k for k, v in state.items() if v.is_floating_point())
    state[name] = state[name] > 0  # a bool tensor of the right shape
    torch.save(state, tmp_path / "bool.pth")
    argv = ["convert", str(tmp_path / "bool.pth"), str(tmp_path / "o.safetensors"), "--model", "nafnet"]
    rc, _, err = run_cli(capsys, [*argv, "--config", json.dumps(TINY_NAFNET)])
    assert rc == 2
    one_error_line(err, "bool.pth", name, "torch.bool")
    assert not (tmp_path / "o.safetensors").exists()


def test_convert_refuses_an_impossible_config_and_a_missing_key(tmp_path, capsys):
    from d2turb.models import create_model

    torch.save(create_model("nafnet", **TINY_NAFNET).state_dict(), tmp_path / "flat.pth")
    argv = ["convert", str(tmp_path / "flat.pth"), str(tmp_path / "o.safetensors"), "--model", "nafnet"]
    rc, _, err = run_cli(capsys, [*argv, "--config", json.dumps({**TINY_NAFNET, "width": -2})])
    assert rc == 2
    one_error_line(err, "flat.pth", "-2")
    rc, _, err = run_cli(capsys, [*argv, "--config", json.dumps(TINY_NAFNET), "--key", "nosuch"])
    assert rc == 2
    one_error_line(err, "flat.pth", "'nosuch'")
    assert not (tmp_path / "o.safetensors").exists()
    assert main([*argv, "--config", json.dumps(TINY_NAFNET)]) == 0  # the same file without --key converts
    capsys.readouterr()
