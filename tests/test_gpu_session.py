"""The GPU lease's script (scripts/gpu_session.py) rehearsed on the CPU: every step but the device (check, pack
build, concurrent benches, concurrent training under the deadline, collection into ≤ 8 files of ≤ 16 MiB), and the
chain across leases: what came back is unpacked into the carried folder here, and the next call starts from it."""

import hashlib
import json
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "gpu_session.py"


def session(*args, timeout=300):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """Call 1 (the default candidate d2turb_small benched, NAFNet alone beside it with a given rate), unpacked into
    the carried folder, then call 2 with the defaults (d2turb_small, its rate given: not benched)."""
    tmp = tmp_path_factory.mktemp("lease")
    runs, carry = tmp / "runs", tmp / "carry"
    common = ["--rehearsal", "--runs", runs, "--carry", carry, "--budget-s", "240"]
    call1 = session("--out", tmp / "out1", *common, "--candidates", "d2turb_small,nafnet_ft", "--rate", "nafnet_ft=40")
    unpacked = session("--unpack", tmp / "out1", "--carry", carry)
    call2 = session("--out", tmp / "out2", *common, "--rate", "d2turb_small=40")
    return tmp, call1, unpacked, call2


def report(out: Path) -> dict:
    return json.loads((out / "gpu_session.json").read_text())


@pytest.mark.slow
def test_rehearsal_runs_every_step_and_brings_back_what_fits(chain, tmp_path):
    """One test per module fixture (xdist would run the fixture once per worker): the steps, then the weights."""
    tmp, call1, _, _ = chain
    out = tmp / "out1"
    assert call1.returncode == 0, call1.stdout[-2000:] + call1.stderr[-2000:]
    files = [p for p in out.iterdir() if p.is_file()]
    assert 0 < len(files) <= 8  # what the device tool brings back
    assert all(p.stat().st_size <= 16 * 2**20 for p in files)
    rep = report(out)
    assert rep["rehearsal"] is True
    assert set(rep["steps"]) >= {"check", "pack", "bench", "train_start", "train_end", "collected"}
    assert rep["steps"]["pack"]["carried"] is False  # built by the same make_pack as on a host without a pack
    benched = rep["steps"]["bench"]["results"]
    assert benched["nafnet_ft"] == {"images_per_s": 40.0, "given": True} and "steps" in benched["d2turb_small"]
    assert set(rep["candidates"]) == {"d2turb_small", "nafnet_ft"}
    for name, cand in rep["candidates"].items():
        assert cand["exit"] == 0 and cand["state"] == "finished", (name, cand)
        assert cand["iteration"] == cand["planned_iterations"]
        last = cand["validation"]["last"]
        assert {f"val_psnr_{b}" for b in ("weak", "medium", "strong")} <= set(last)
        assert cand["start"] == {"calls_before": 0, "from": "nafnet-gpu-spectral3", "carried": False,
                                 "previous_calls": []}  # fmt: skip
    check_weights_load_strictly_and_restore(out, tmp_path)
    check_backbone_started_from_the_shipped_nafnet(out)


@pytest.mark.slow
def test_the_next_call_continues_from_the_carried_weights(chain):
    tmp, call1, unpacked, call2 = chain
    assert call1.returncode == 0 and unpacked.returncode == 0, unpacked.stderr
    assert call2.returncode == 0, call2.stdout[-2000:] + call2.stderr[-2000:]
    carried = (tmp / "carry" / "d2turb_small").resolve()
    with tarfile.open(tmp / "out1" / "d2turb_small.tar") as tar:
        weights1 = tar.extractfile("d2turb_small/model.safetensors").read()
    assert (carried / "model.safetensors").read_bytes() == weights1
    rep = report(tmp / "out2")
    assert set(rep["candidates"]) == {"d2turb_small"}  # the default
    cand = rep["candidates"]["d2turb_small"]
    assert cand["exit"] == 0 and cand["state"] == "finished"
    start = cand["start"]
    assert start["carried"] and start["calls_before"] == 1
    assert start["from"] == str(carried / "model.safetensors")
    assert start["sha256"] == hashlib.sha256(weights1).hexdigest()
    assert "train.seed=1009" in cand["set"]  # a new seed: other crops and turbulence than call 1's
    with tarfile.open(tmp / "out2" / "d2turb_small.tar") as tar:
        state = json.loads(tar.extractfile("d2turb_small/lease_state.json").read())
        weights2 = tar.extractfile("d2turb_small/model.safetensors").read()
    assert [c["call"] for c in state["calls"]] == [1, 2]
    assert [c["seed"] for c in state["calls"]] == [0, 1009]
    assert state["calls"][0]["from"] == "nafnet-gpu-spectral3"
    assert state["calls"][1]["from_sha256"] == hashlib.sha256(weights1).hexdigest()
    assert state["weights_sha256"] == hashlib.sha256(weights2).hexdigest() != state["calls"][1]["from_sha256"]
    assert state["iterations_total"] == sum(c["iterations"] for c in state["calls"]) == 2 * cand["iteration"]
    # here again: call 2 unpacks over call 1; call 1's tar is refused now (it does not continue the carried state)
    assert session("--unpack", tmp / "out2", "--carry", tmp / "carry").returncode == 0
    assert json.loads((carried / "lease_state.json").read_text()) == state
    stale = session("--unpack", tmp / "out1", "--carry", tmp / "carry")
    assert stale.returncode == 2 and "does not continue" in stale.stderr
    assert (carried / "model.safetensors").read_bytes() == weights2


def check_weights_load_strictly_and_restore(out, tmp_path):
    import torch

    from d2turb.models import load_pretrained

    for name in report(out)["candidates"]:
        with tarfile.open(out / f"{name}.tar") as tar:
            members = {Path(m.name).name for m in tar.getmembers()}
            assert {"model.safetensors", "lease_state.json", "log.jsonl", "config.yaml"} <= members
            (tmp_path / f"{name}.safetensors").write_bytes(tar.extractfile(f"{name}/model.safetensors").read())
        model = load_pretrained(tmp_path / f"{name}.safetensors")  # checksum and strict keys/shapes/dtypes
        x = torch.rand(1, 3, 32, 48)
        with torch.no_grad():
            y = model(x)["restored"]
        assert y.shape == x.shape and torch.isfinite(y).all()


def check_backbone_started_from_the_shipped_nafnet(out):
    """Four small steps move no weight far: d2turb_small's backbone is still the shipped NAFNet's to within 1e-2,
    while a fresh initialisation differs from it by far more."""
    from safetensors.torch import load

    from d2turb.models import create_model
    from d2turb.models.hub import resolve_weights

    with tarfile.open(out / "d2turb_small.tar") as tar:
        trained = load(tar.extractfile("d2turb_small/model.safetensors").read())
    shipped = load(Path(resolve_weights("nafnet-gpu-spectral3")).read_bytes())
    fresh = create_model("d2turb_small").state_dict()
    backbone = [k for k in trained if k.startswith("backbone.")]
    assert len(backbone) == len(shipped) > 10
    drift = max((trained[k] - shipped[k]).abs().max().item() for k in backbone)
    fresh_gap = max((fresh[k] - shipped[k]).abs().max().item() for k in backbone)
    assert drift < 1e-2 < fresh_gap, (drift, fresh_gap)


def test_carry_size_counts_the_checkout_and_the_carried_paths(tmp_path):
    """The size a call would carry, against git's own list of the files that travel plus the named folder."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, check=True).stdout.split(b"\0")  # fmt: skip
    base = sum((ROOT / f.decode()).stat().st_size for f in files if f and (ROOT / f.decode()).is_file())
    done = session("--carry-size", "scripts", timeout=60)  # tracked already: counted once
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"{base / 2**20:.1f} MiB of 64: fits")
