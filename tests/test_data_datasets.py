"""PairDataset (augmentation keeps flow consistent), CleanCropDataset and OnTheFlySynthesis."""

import json
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hostile_input import error_lines, one_error_line, rgb, run_cli, tiny_config, tiny_pairs
from PIL import Image
from scipy import stats

from d2turb.cli import main
from d2turb.data import CleanCropDataset, OnTheFlySynthesis, PairDataset, crop_sample, flip_sample
from d2turb.data.layout import BIN_NAMES, write_depth_png
from d2turb.errors import D2TurbError
from d2turb.io import read_image, write_image, write_json, write_npy
from d2turb.ops import warp
from d2turb.sim import BINS, dr0_bin

P = 48


def smooth_field(gen, channels, size, scale):
    coarse = torch.randn(1, channels, 6, 6, generator=gen)
    return F.interpolate(coarse, size=(size, size), mode="bicubic", align_corners=True)[0] * scale


@pytest.fixture
def handmade(tmp_path):
    """A 2-sample dataset with an exactly known backward flow: gt = warp(tilt, flow)."""
    gen = torch.Generator().manual_seed(0)
    root = tmp_path / "train"
    write_json(
        root / "dataset.json",
        {
            "version": 1,
            "pairs": 2,
            "patch": P,
            "split": "train",
            "bins": list(BIN_NAMES),
            "bin_ranges": {k: list(v) for k, v in BINS.items()},
        },
    )
    lines = []
    for k, dr0 in enumerate([1.5, 4.2]):
        sid = f"{k:07d}"
        tilt = (smooth_field(gen, 3, P, 0.25) + 0.5).clamp(0, 1)
        tilt = (tilt * 255).round() / 255
        flow = smooth_field(gen, 2, P, 2.0).half().float()
        gt = warp(tilt[None], flow[None])[0]
        write_image(root / "tilt" / f"{sid}.png", tilt)
        write_image(root / "turb" / f"{sid}.png", tilt)
        write_image(root / "gt" / f"{sid}.png", gt)
        write_npy(root / "bwd_flow_px" / f"{sid}.npy", flow.numpy().astype(np.float16))
        write_depth_png(root / "depth" / f"{sid}.png", torch.linspace(0, 1, P).view(1, P, 1).expand(1, P, P))
        lines.append(json.dumps({"id": sid, "index": k, "dr0": dr0, "bin": dr0_bin(dr0)}) + "\n")
    (root / "meta.jsonl").write_text("".join(lines))
    return root


def warp_error(s):
    return (warp(s["tilt"][None], s["bwd_flow_px"][None])[0] - s["gt"]).abs().max().item()


def test_pair_dataset_items(handmade):
    ds = PairDataset(handmade, split="train")
    assert len(ds) == 2
    s = ds[1]
    assert s["turb"].shape == s["tilt"].shape == s["gt"].shape == (3, P, P)
    assert s["bwd_flow_px"].shape == (2, P, P) and s["bwd_flow_px"].dtype == torch.float32
    assert s["depth"].shape == (1, P, P) and s["depth"][0, -1, 0] == 1.0 and s["depth"][0, 0, 0] == 0.0
    assert s["dr0"].item() == pytest.approx(4.2) and BIN_NAMES[s["bin"].item()] == "strong" and s["id"] == "0000001"
    assert warp_error(s) < 1.5 / 255  # only the 8-bit rounding of gt
    batch = torch.utils.data.default_collate([ds[0], ds[1]])
    assert batch["gt"].shape == (2, 3, P, P) and batch["bin"].tolist() == [0, 2]
    assert set(s) == set(batch) and "flow" not in set(s)  # one key per tensor
    with pytest.warns(DeprecationWarning, match=r"dataset sample\['flow'\]"):
        assert batch["flow"] is batch["bwd_flow_px"]  # a batch keeps the deprecated name readable
    assert len(PairDataset(handmade.parent, split="train")) == 2  # parent folder holding train/
    with pytest.raises(D2TurbError, match="split is 'train', not 'test'"):
        PairDataset(handmade, split="test")


@pytest.mark.parametrize("horizontal", [True, False])
def test_flip_keeps_flow_consistent(handmade, horizontal):
    s = PairDataset(handmade)[0]
    flipped = flip_sample(s, horizontal=horizontal)
    assert warp_error(flipped) < 1.5 / 255
    # the oracle can fail: mirroring the flow field without negating its component breaks the identity
    naive = dict(flipped, bwd_flow_px=s["bwd_flow_px"].flip(-1 if horizontal else -2))
    assert warp_error(naive) > 20 / 255
    assert torch.equal(flip_sample(flipped, horizontal=horizontal)["bwd_flow_px"], s["bwd_flow_px"])
    assert "flow" not in set(s) and "flow" not in set(flipped)  # one key per tensor
    with pytest.warns(DeprecationWarning, match="bwd_flow_px"):  # the deprecated name still reads it
        assert s["flow"] is s["bwd_flow_px"] and flipped["flow"] is flipped["bwd_flow_px"]
    plain = {k: v for k, v in s.items() if k != "bwd_flow_px"} | {"flow": s["bwd_flow_px"]}  # an old dict
    old = flip_sample(plain, horizontal=horizontal)
    assert torch.equal(old["flow"], flipped["bwd_flow_px"]) and "bwd_flow_px" not in old


def test_random_crop_and_flip_augmentation(handmade):
    torch.manual_seed(0)
    ds = PairDataset(handmade, crop=32, hflip=True, vflip=True)
    full = PairDataset(handmade)[0]
    for _ in range(6):
        s = ds[0]
        assert s["gt"].shape == (3, 32, 32) and s["bwd_flow_px"].shape == (2, 32, 32)
        # interior check: a crop moves the image border that the warp clamps to
        m = int(s["bwd_flow_px"].abs().max().ceil()) + 1
        inner = (warp(s["tilt"][None], s["bwd_flow_px"][None])[0] - s["gt"])[:, m:-m, m:-m].abs().max().item()
        assert inner < 1.5 / 255
    c = crop_sample(full, 5, 7, 20)
    assert torch.equal(c["bwd_flow_px"], full["bwd_flow_px"][:, 5:25, 7:27])
    assert torch.equal(c["depth"], full["depth"][:, 5:25, 7:27])
    with pytest.raises(D2TurbError, match="crop 64"):
        PairDataset(handmade, crop=64)


@pytest.fixture
def clean_dir(tmp_path):
    from skimage import data

    folder = tmp_path / "clean"
    folder.mkdir()
    Image.fromarray(data.astronaut()[::4, ::4]).save(folder / "astronaut.png")
    Image.fromarray(data.camera()[::12, ::12]).save(folder / "camera.png")  # 43x43 < patch
    return folder


def test_clean_crop_dataset_crops_image_and_depth_together(clean_dir):
    from d2turb.data.sources import resize_up
    from d2turb.depth.prior import estimate_depth_prior

    torch.manual_seed(1)
    ds = CleanCropDataset([clean_dir], patch=P, depth_spec="prior", length=6, hflip=False)
    assert len(ds) == 6
    for i in range(len(ds)):
        s = ds[i]
        assert s["gt"].shape == (3, P, P) and s["depth"].shape == (1, P, P)
        stem, xy = s["id"].split("@")
        x0, y0 = map(int, xy.split(","))
        image = read_image(clean_dir / f"{stem}.png")
        depth = resize_up(estimate_depth_prior(image).reshape(1, *image.shape[-2:]), P)
        image = resize_up(image, P)
        assert torch.allclose(s["gt"], image[:, y0 : y0 + P, x0 : x0 + P])
        assert torch.allclose(s["depth"], depth[:, y0 : y0 + P, x0 : x0 + P])
    assert CleanCropDataset([clean_dir], patch=P, depth_spec="none")[0]["depth"].eq(1).all()


def _simulator():
    from d2turb.sim import Simulator, TurbulenceParams

    return Simulator(TurbulenceParams(), device="cpu")


def test_sample_dr0_is_uniform_over_union():
    synth = OnTheFlySynthesis(simulator=None, bins=("weak", "strong"), seed=0)
    v = synth.sample_dr0(4000).double().numpy()
    assert (((v >= 1) & (v <= 2.25)) | ((v >= 3.75) & (v <= 5))).all()
    folded = np.where(v <= 2.25, v - 1.0, v - 3.75 + 1.25)
    assert stats.kstest(folded, stats.uniform(0, 2.5).cdf).pvalue > 1e-3
    with pytest.raises(D2TurbError, match="unknown bin 'mild'"):
        OnTheFlySynthesis(simulator=None, bins=("mild",))


def test_on_the_fly_synthesis(clean_dir):
    simulator = _simulator()
    torch.manual_seed(0)
    loader = torch.utils.data.DataLoader(
        CleanCropDataset([clean_dir], patch=P, depth_spec="prior", length=4), batch_size=4
    )
    batch = next(iter(loader))
    synth = OnTheFlySynthesis(simulator, bins=("strong",), device="cpu", seed=3)
    a, b = synth(batch), synth(batch)
    for key, shape in [
        ("turb", (4, 3, P, P)),
        ("tilt", (4, 3, P, P)),
        ("gt", (4, 3, P, P)),
        ("bwd_flow_px", (4, 2, P, P)),
        ("depth", (4, 1, P, P)),
    ]:
        assert a[key].shape == shape
    assert ((a["dr0"] >= 3.75) & (a["dr0"] <= 5)).all() and (a["bin"] == BIN_NAMES.index("strong")).all()
    assert not torch.equal(a["tilt"], b["tilt"])  # new turbulence on every call
    assert torch.equal(a["gt"], batch["gt"]) and a["id"] == batch["id"]
    inner = (slice(None), slice(None), slice(6, -6), slice(6, -6))
    err_flow = (warp(a["tilt"], a["bwd_flow_px"]) - a["gt"])[inner].abs().mean()
    err_none = (a["tilt"] - a["gt"])[inner].abs().mean()
    assert err_flow < 0.8 * err_none  # the returned flow is the backward flow: it undoes the tilt
    again = OnTheFlySynthesis(simulator, bins=("strong",), device="cpu", seed=3)(batch)
    assert torch.equal(again["turb"], a["turb"])  # seeded: reproducible


def test_a_dataset_of_the_earlier_layout_still_reads_with_a_warning(handmade, capsys):
    """Datasets written before issue 39 hold the backward flows in flow/<id>.npy: read as bwd_flow_px, warning once."""
    new = PairDataset(handmade)[1]
    (handmade / "bwd_flow_px").rename(handmade / "flow")
    with pytest.warns(DeprecationWarning, match="earlier layout"):
        old = PairDataset(handmade)[1]
    assert torch.equal(old["bwd_flow_px"], new["bwd_flow_px"]) and warp_error(old) < 1.5 / 255
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process
        PairDataset(handmade)[0]
    assert main(["check-dataset", str(handmade)]) == 0, capsys.readouterr()


@pytest.mark.parametrize("bad_id", ["/etc/passwd", "a/b", "..", ".hidden", "", 7, None])
def test_meta_ids_must_be_plain_names(bad_id, tmp_path):
    from d2turb.data import PairDataset
    from d2turb.errors import D2TurbError

    root = tiny_pairs(tmp_path / "ds", n=1, size=16)
    (root / "meta.jsonl").write_text(json.dumps({"id": bad_id, "index": 0, "dr0": 2.0, "bin": "weak"}) + "\n")
    with pytest.raises(D2TurbError, match="meta.jsonl line 1"):
        PairDataset(root)


def test_a_meta_id_that_leaves_the_dataset_is_refused(tmp_path, capsys):
    root = tmp_path / "deep" / "ds"
    tiny_pairs(root, n=2, size=16, split="test")
    assert main(["check-dataset", str(root)]) == 0
    # root/turb/../../secret.png, root/flow/../../secret.npy: the files a traversal would read
    rgb(tmp_path / "deep" / "secret.png", 16, 16, seed=9)
    np.save(tmp_path / "deep" / "secret.npy", np.zeros((2, 16, 16), np.float16))
    good = {"id": "0000000", "index": 0, "dr0": 2.0, "bin": "weak", "split": "test"}
    evil = {"id": "../../secret", "index": 1, "dr0": 2.0, "bin": "weak", "split": "test"}
    (root / "meta.jsonl").write_text(json.dumps(good) + "\n" + json.dumps(evil) + "\n")
    argv = ["evaluate", "--data", str(root), "--weights", "input", "--metrics", "psnr", "--out", str(tmp_path / "o")]
    rc, _, err = run_cli(capsys, argv)
    # the record is refused (never read) and skipped with its error line, the good one evaluated (issue 37)
    assert rc == 1 and "Traceback" not in err
    (line,) = error_lines(err)
    assert "meta.jsonl line 2" in line and "../../secret" in line
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert [s["id"] for s in results["per_sample"]] == ["0000000"] and len(results["skipped"]) == 1
    rc, out, err = run_cli(capsys, ["check-dataset", str(root)])
    assert rc == 1 and "../../secret" in err and "ok" not in out.split()


GOOD_RECORD = {"id": "0000000", "index": 0, "dr0": 2.0, "bin": "weak", "split": "test"}


@pytest.mark.parametrize(
    "damage, words",
    [
        ({"meta": {k: v for k, v in GOOD_RECORD.items() if k != "index"}}, ["meta.jsonl line 1", "index"]),
        ({"meta": {k: v for k, v in GOOD_RECORD.items() if k != "dr0"}}, ["meta.jsonl line 1", "dr0"]),
        ({"meta": {**GOOD_RECORD, "index": "zero"}}, ["meta.jsonl line 1", "index"]),
        ({"meta": {**GOOD_RECORD, "index": 1.5}}, ["meta.jsonl line 1", "index"]),
        ({"meta": {**GOOD_RECORD, "dr0": "strong"}}, ["meta.jsonl line 1", "dr0"]),
        ({"meta": [1, 2]}, ["meta.jsonl line 1"]),
        ({"config": {"version": 1, "pairs": 2, "patch": "16", "split": "test"}}, ["dataset.json", "patch"]),
        ({"config": {"version": 1, "pairs": 2, "patch": 16.5, "split": "test"}}, ["dataset.json", "patch"]),
        ({"config": [1, 2, 3]}, ["dataset.json", "object"]),
    ],
)
def test_damaged_dataset_files_are_one_line_everywhere(damage, words, tmp_path, capsys):
    root = tiny_pairs(tmp_path / "ds", n=2, size=16, split="test")
    if "meta" in damage:
        second = {**GOOD_RECORD, "id": "0000001", "index": 1}
        (root / "meta.jsonl").write_text(json.dumps(damage["meta"]) + "\n" + json.dumps(second) + "\n")
    else:
        (root / "dataset.json").write_text(json.dumps(damage["config"]))
    argv = ["evaluate", "--data", str(root), "--weights", "input", "--metrics", "psnr", "--out", str(tmp_path / "o")]
    rc, _, err = run_cli(capsys, argv)
    if "meta" in damage:  # evaluate skips a bad record with its error line and evaluates the others (issue 37)
        assert rc == 1 and "Traceback" not in err
        (line,) = error_lines(err)
        assert all(word in line for word in words), line
        assert json.loads((tmp_path / "o" / "results.json").read_text())["samples_evaluated"] == 1
    else:
        assert rc == 2
        one_error_line(err, *words)
    config = tiny_config(tmp_path)  # training with this folder as val.pairs
    argv = ["train", "--config", str(config), "--out", str(tmp_path / "run"), "--set", f"val.pairs={root}"]
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, *words)
    rc, out, err = run_cli(capsys, ["check-dataset", str(root)])  # the same checks: never "ok"
    assert rc in (1, 2) and "ok" not in out.split() and "Traceback" not in err
    assert words[0] in err
