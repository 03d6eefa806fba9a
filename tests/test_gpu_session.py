"""The GPU lease's script (scripts/gpu_session.py) rehearsed on the CPU: every step but the device (check, pack
build, concurrent benches, concurrent training under the deadline, collection into ≤ 8 files of ≤ 16 MiB)."""

import json
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rehearsal(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lease")
    out, runs = tmp / "out", tmp / "runs"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gpu_session.py"), "--rehearsal", "--out", str(out)]
        + ["--runs", str(runs), "--budget-s", "240", "--candidates", "nafnet_ft,nafnet_w24"]  # two side by side
        + ["--rate", "nafnet_w24=40"],  # one with a rate measured before: not benched
        capture_output=True,
        text=True,
        timeout=300,
    )
    return proc, out, runs


@pytest.mark.slow
def test_rehearsal_runs_every_step_and_brings_back_what_fits(rehearsal, tmp_path):
    """One test (xdist would run a module fixture once per worker): the steps, then the weights that came back."""
    proc, out, _ = rehearsal
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    files = [p for p in out.iterdir() if p.is_file()]
    assert 0 < len(files) <= 8  # what the device tool brings back
    assert all(p.stat().st_size <= 16 * 2**20 for p in files)
    report = json.loads((out / "gpu_session.json").read_text())
    assert report["rehearsal"] is True
    assert set(report["steps"]) >= {"check", "pack", "bench", "train_start", "train_end", "collected"}
    assert report["steps"]["pack"]["carried"] is False  # built by the same make_pack as on a host without a pack
    benched = report["steps"]["bench"]["results"]
    assert benched["nafnet_w24"] == {"images_per_s": 40.0, "given": True} and "steps" in benched["nafnet_ft"]
    assert report["candidates"], "no candidate trained"
    for name, cand in report["candidates"].items():
        assert cand["exit"] == 0 and cand["state"] == "finished", (name, cand)
        assert cand["iteration"] == cand["planned_iterations"]
        last = cand["validation"]["last"]
        assert {f"val_psnr_{b}" for b in ("weak", "medium", "strong")} <= set(last)
    check_weights_load_strictly_and_restore(out, tmp_path)


def check_weights_load_strictly_and_restore(out, tmp_path):
    import torch

    from d2turb.models import load_pretrained

    report = json.loads((out / "gpu_session.json").read_text())
    for name in report["candidates"]:
        with tarfile.open(out / f"{name}.tar") as tar:
            members = {Path(m.name).name for m in tar.getmembers()}
            assert {"best.safetensors", "log.jsonl", "config.yaml"} <= members
            (tmp_path / f"{name}.safetensors").write_bytes(tar.extractfile(f"{name}/best.safetensors").read())
        model = load_pretrained(tmp_path / f"{name}.safetensors")  # checksum and strict keys/shapes/dtypes
        x = torch.rand(1, 3, 32, 48)
        with torch.no_grad():
            y = model(x)["restored"]
        assert y.shape == x.shape and torch.isfinite(y).all()
