"""Issue 39: every flow file says its direction and unit, and holds what its name says (docs/flow.md).

Per output kind, on a small simulated case whose flow is known: the file's flow, applied in its stated direction,
brings the frame closer to its reference than the opposite sign does.

- forward Δ (``*_fwd_flow_px``): frame(x) ≈ ref(x + Δ(x)), i.e. warp(ref, Δ) ≈ frame;
- backward V (``*_bwd_flow_px``): warp(frame, V) ≈ ref.
"""

import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from d2turb.cli import main
from d2turb.data import PairDataset
from d2turb.io import read_image, write_image
from d2turb.models import model_output
from d2turb.ops import invert_flow, warp

SIZE = 64
INNER = (..., slice(8, -8), slice(8, -8))  # away from the border, where warps clamp


def err(a, b) -> float:
    return float((a - b)[INNER].abs().mean())


def scene(path, size=SIZE, seed=0):
    g = torch.Generator().manual_seed(seed)
    img = F.interpolate(torch.rand(1, 3, size // 4, size // 4, generator=g), size=(size, size), mode="bicubic")
    write_image(path, img[0].clamp(0, 1))
    return path


def npy(path) -> torch.Tensor:
    return torch.from_numpy(np.load(path)).float()[None]


def assert_forward(flow, ref, frame):
    """frame ≈ warp(ref, flow), and clearly better than with −flow."""
    right, wrong = err(warp(ref, flow), frame), err(warp(ref, -flow), frame)
    assert right < 0.7 * wrong, (right, wrong)


def assert_backward(flow, frame, ref):
    """warp(frame, flow) ≈ ref, and clearly better than with −flow."""
    right, wrong = err(warp(frame, flow), ref), err(warp(frame, -flow), ref)
    assert right < 0.7 * wrong, (right, wrong)


def test_simulate_writes_the_forward_flow_as_fwd_flow_px(tmp_path, capsys):
    image = scene(tmp_path / "a.png")
    out = tmp_path / "sim"
    assert main(["simulate", str(image), "--out", str(out), "--dr0", "4", "--seed", "2", "--save-flow"]) == 0
    capsys.readouterr()
    assert not list(out.glob("*_flow.npy")) or sorted(p.name for p in out.glob("*flow*")) == ["a_fwd_flow_px.npy"]
    fwd = npy(out / "a_fwd_flow_px.npy")
    clean, tilt = read_image(image)[None], read_image(out / "a_tilt.png")[None]
    assert fwd.abs().mean() > 0.5  # a flow worth checking
    assert_forward(fwd, clean, tilt)
    assert_backward(invert_flow(fwd), tilt, clean)  # and its inverse undoes the tilt


def test_simulate_video_writes_forward_flows_in_fwd_flow_px(tmp_path, capsys):
    image = scene(tmp_path / "a.png")
    out = tmp_path / "clip"
    args = ["simulate-video", str(image), "--out", str(out), "--frames", "3", "--no-mp4", "--dr0", "4"]
    assert main([*args, "--save-flow", "--save-tilt", "--seed", "1"]) == 0
    capsys.readouterr()
    assert not (out / "flow").exists() and len(list((out / "fwd_flow_px").glob("*.npy"))) == 3
    clean = read_image(image)[None]
    for i in range(3):
        fwd = npy(out / "fwd_flow_px" / f"{i:06d}.npy")
        assert_forward(fwd, clean, read_image(out / "tilt" / f"{i:06d}.png")[None])


def test_simulate_video_rerun_removes_an_earlier_versions_flow_folder(tmp_path, capsys):
    image = scene(tmp_path / "a.png", size=24)
    out = tmp_path / "clip"
    (out / "flow").mkdir(parents=True)
    np.save(out / "flow" / "000000.npy", np.zeros((2, 24, 24), np.float32))  # written before issue 39
    assert main(["simulate-video", str(image), "--out", str(out), "--frames", "2", "--no-mp4", "--save-flow"]) == 0
    capsys.readouterr()
    assert not (out / "flow").exists() and len(list((out / "fwd_flow_px").iterdir())) == 2


class KnownFlow(nn.Module):
    """A restoration model that knows the simulator's backward flow of its input (deblurred = input)."""

    def __init__(self, bwd):
        super().__init__()
        self.bwd = bwd

    def forward(self, x):
        return model_output(x, warp(x, self.bwd), self.bwd)


def test_restore_writes_the_backward_flow_as_bwd_flow_px(tmp_path, capsys):
    image = scene(tmp_path / "a.png")
    sim = tmp_path / "sim"
    assert main(["simulate", str(image), "--out", str(sim), "--dr0", "4", "--seed", "2", "--save-flow"]) == 0
    capsys.readouterr()
    from d2turb.restore.files import restore_files

    fwd = npy(sim / "a_fwd_flow_px.npy")
    tilt_path = sim / "a_tilt.png"
    out = tmp_path / "res"
    assert restore_files([tilt_path], out, KnownFlow(invert_flow(fwd)), tile=1024, save_flow=True) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.glob("*flow*")) == ["a_tilt_bwd_flow_px.npy"]
    bwd = npy(out / "a_tilt_bwd_flow_px.npy")
    torch.testing.assert_close(bwd, invert_flow(fwd), atol=1e-5, rtol=0)
    clean, tilt = read_image(image)[None], read_image(tilt_path)[None]
    assert_backward(bwd, tilt, clean)
    assert err(read_image(out / "a_tilt_restored.png")[None], clean) < 0.7 * err(tilt, clean)


def test_restore_temporal_writes_forward_flows_in_fwd_flow_px(tmp_path, capsys):
    """A clip of tilt-only frames of a still scene: the temporal reference is close to the clean scene, so each
    frame's fwd_flow_px (frame(x) ≈ restored(x + Δ(x))) follows the simulator's forward Δ of that frame."""
    image = scene(tmp_path / "a.png", size=96)
    clip = tmp_path / "clip"
    args = ["simulate-video", str(image), "--out", str(clip), "--frames", "6", "--no-mp4", "--dr0", "4"]
    assert main([*args, "--save-flow", "--save-tilt", "--seed", "3", "--boil", "1"]) == 0
    out = tmp_path / "res"
    rc = main(["restore", str(clip / "tilt"), "--temporal", "6", "--deblur", "none", "--out", str(out), "--save-flow"])
    capsys.readouterr()
    assert rc == 0 and not (out / "flow").exists()
    sim = torch.stack([npy(clip / "fwd_flow_px" / f"{i:06d}.npy")[0] for i in range(6)])
    mean = sim.mean(0, keepdim=True)  # the reference sits near the frames' mean position
    for i in range(6):
        fwd = npy(out / "fwd_flow_px" / f"{i:06d}.npy")
        frame = read_image(clip / "tilt" / f"{i:06d}.png")[None]
        restored = read_image(out / f"{i:06d}_restored.png")[None]
        assert_forward(fwd, restored, frame)
        truth = sim[i : i + 1] - mean
        assert err(fwd, truth) < 0.7 * err(-fwd, truth), (err(fwd, truth), err(-fwd, truth))


def test_make_dataset_writes_backward_flows_in_bwd_flow_px(tmp_path, capsys):
    clean = tmp_path / "clean"
    clean.mkdir()
    scene(clean / "a.png", size=96)
    out = tmp_path / "ds"
    args = ["make-dataset", "--clean", str(clean), "--out", str(out), "--pairs", "2", "--patch", "48"]
    assert main([*args, "--batch", "2", "--depth", "none", "--bins", "strong", "--device", "cpu"]) == 0
    capsys.readouterr()
    assert not (out / "flow").exists() and len(list((out / "bwd_flow_px").glob("*.npy"))) == 2
    for s in PairDataset(out):
        assert set(s) >= {"bwd_flow_px", "tilt", "gt"} and "flow" not in set(s)
        assert s["bwd_flow_px"].abs().mean() > 0.3
        assert_backward(s["bwd_flow_px"][None], s["tilt"][None], s["gt"][None])
    with pytest.warns(DeprecationWarning):
        assert s["flow"] is s["bwd_flow_px"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        PairDataset(out)[0]["bwd_flow_px"]  # the new names never warn
