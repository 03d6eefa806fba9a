"""d2turb.train: loss terms vs hand computation, configs, training loop, resume, DDP, atomic checkpoints, CLI."""

import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hostile_input import dead_pid, one_error_line, run_cli, run_d2turb, tiny_config

from d2turb.cli import main
from d2turb.errors import D2TurbError
from d2turb.train import Config, MultiStageLoss, PerceptualLoss, Trainer, build_loss, load_config, psnr_loss
from d2turb.train.losses import native_loss_name

REPO = Path(__file__).resolve().parents[1]
TINY_MODEL = {
    "name": "d2turb",
    "backbone": "nafnet",
    "injection": "aspi_cosine",
    "rectifier": "unet",
    "backbone_cfg": {"width": 8, "enc_blocks": [1, 1], "dec_blocks": [1, 1], "middle_blocks": 1},
    "rectifier_cfg": {"width": 8, "mults": [1, 2, 2, 2], "depth": 3},
}


def make_pairs(root: Path, n: int = 8, size: int = 32, seed: int = 0, split: str = "train") -> Path:
    """A tiny PairDataset on disk: smooth random gt, smooth random backward flow, tilt = gt warped by −flow."""
    from d2turb.data.layout import write_depth_png
    from d2turb.io import write_image
    from d2turb.ops import warp

    g = torch.Generator().manual_seed(seed)
    for kind in ("turb", "tilt", "gt", "bwd_flow_px", "depth"):
        (root / kind).mkdir(parents=True, exist_ok=True)
    lines = []
    for i in range(n):
        sid = f"{i:07d}"
        gt = F.interpolate(
            torch.rand(1, 3, size // 4, size // 4, generator=g), size=(size, size), mode="bilinear", align_corners=True
        )
        flow = F.interpolate(
            torch.randn(1, 2, 4, 4, generator=g), size=(size, size), mode="bilinear", align_corners=True
        )
        tilt = warp(gt, -flow).clamp(0, 1)
        turb = F.avg_pool2d(F.pad(tilt, (1, 1, 1, 1), mode="replicate"), 3, 1)
        for kind, image in (("turb", turb), ("tilt", tilt), ("gt", gt)):
            write_image(root / kind / f"{sid}.png", image[0])
        np.save(root / "bwd_flow_px" / f"{sid}.npy", flow[0].numpy().astype(np.float16))
        write_depth_png(root / "depth" / f"{sid}.png", torch.rand(1, size, size, generator=g))
        lines.append(json.dumps({"id": sid, "index": i, "dr0": 2.0, "bin": "weak"}))
    (root / "dataset.json").write_text(json.dumps({"version": 1, "patch": size, "split": split}))
    (root / "meta.jsonl").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture(scope="module")
def pairs(tmp_path_factory) -> Path:
    return make_pairs(tmp_path_factory.mktemp("pairs"))


@pytest.fixture(autouse=True)
def _one_thread(_torch_threads):
    """Tiny models on 32² images: one thread is faster than two (and immune to a busy machine)."""
    torch.set_num_threads(1)


def tiny_cfg(pairs: Path, data: dict | None = None, val: dict | None = None, **train) -> Config:
    base = {
        "model": TINY_MODEL,
        "data": {"pairs": str(pairs), "patch": 32, "num_workers": 0, "hflip": False, **(data or {})},
        "train": {"iterations": 4, "batch": 4, "lr": 1e-3, "device": "cpu", **train},
        "loss": {"vgg": 0.0},
        "val": val or {},
        "log": {"every": 1, "progress": False},
        "checkpoint": {"every": 1000},
    }
    return load_config(base=base)


def fake_batch(b=2, h=12, w=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    out = {"deblurred": r(b, 3, h, w), "restored": r(b, 3, h, w), "bwd_flow_px": 3 * r(b, 2, h, w) - 1.5}
    batch = {"tilt": r(b, 3, h, w), "gt": r(b, 3, h, w), "bwd_flow_px": 3 * r(b, 2, h, w) - 1.5}
    return out, batch


# ------------------------------------------------------------------ losses
def test_multistage_loss_matches_hand_computation():
    out, batch = fake_batch()
    n = lambda t: t.double().numpy()  # noqa: E731
    deblur = np.abs(n(out["deblurred"]) - n(batch["tilt"])).mean()  # Eq. 11 (L1)
    flow = np.abs(n(out["bwd_flow_px"]) - n(batch["bwd_flow_px"])).mean()  # Eq. 12
    photo = np.abs(n(out["restored"]) - n(batch["gt"])).mean()  # Eq. 13 without VGG
    total, terms = MultiStageLoss()(out, batch)  # defaults: λ_flow 5, λ_photo 1, no perceptual module
    assert total.item() == pytest.approx(deblur + 5.0 * flow + photo, rel=1e-5)
    assert terms["deblur"] == pytest.approx(deblur, rel=1e-5) and terms["flow"] == pytest.approx(flow, rel=1e-5)
    total0, _ = MultiStageLoss(deblur=0.0)(out, batch)  # "w/o L_deblur"
    assert total0.item() == pytest.approx(5.0 * flow + photo, rel=1e-5)


def test_plain_backbone_trains_on_clean_target_only():
    out, batch = fake_batch()
    out["bwd_flow_px"] = None
    total, terms = MultiStageLoss()(out, batch)
    assert set(terms) == {"photo"}
    assert total.item() == pytest.approx(np.abs(out["restored"].numpy() - batch["gt"].numpy()).mean(), rel=1e-5)


def test_plain_backbone_with_explicit_native_loss_uses_it_against_clean():
    from d2turb.eval.metrics import psnr
    from d2turb.models import create_model

    out, batch = fake_batch(b=3)
    out["bwd_flow_px"] = None
    loss = MultiStageLoss(photo=2.0, plain="psnr")
    total, terms = loss(out, batch)
    assert set(terms) == {"photo"}
    assert total.item() == pytest.approx(-2.0 * psnr(out["restored"], batch["gt"]).mean().item(), rel=1e-5)
    model = create_model("nafnet", width=8, enc_blocks=(1,), dec_blocks=(1,), middle_blocks=1)
    assert build_loss({"native": "psnr"}, model).plain == "psnr"
    assert build_loss({}, model).plain == "l1"  # no explicit native loss: L1 as in Table 1
    with pytest.raises(D2TurbError, match="unknown native loss"):
        MultiStageLoss(plain="l3")


def test_psnr_native_loss_is_minus_psnr():
    from d2turb.eval.metrics import psnr

    out, batch = fake_batch(b=3)
    assert psnr_loss(out["deblurred"], batch["tilt"]).item() == pytest.approx(
        -psnr(out["deblurred"], batch["tilt"]).mean().item(), rel=1e-5
    )
    loss = MultiStageLoss(native="psnr", flow=0.0, photo=0.0)
    assert loss(out, batch)[0].item() == pytest.approx(-psnr(out["deblurred"], batch["tilt"]).mean().item(), rel=1e-5)


def test_spectral_amplitude_loss_numpy_and_shift_invariance():
    from d2turb.train.losses import spectral_amplitude_loss

    out, batch = fake_batch(b=2)
    pred, gt = out["restored"], batch["gt"]
    amp = lambda t: np.abs(np.fft.rfft2(t.double().numpy(), norm="ortho"))  # noqa: E731  numpy's FFT as the oracle
    expected = np.abs(amp(pred) - amp(gt)).mean()
    assert spectral_amplitude_loss(pred, gt).item() == pytest.approx(expected, rel=1e-5)
    # Fourier shift theorem: a circular shift changes the phase only, so the amplitude loss ignores it ...
    shifted = torch.roll(gt, shifts=(3, -5), dims=(2, 3))
    assert spectral_amplitude_loss(shifted, gt).item() == pytest.approx(0.0, abs=1e-6)
    assert np.abs(shifted.numpy() - gt.numpy()).mean() > 0.05  # ... which the pixel loss does not
    # a blur lowers the amplitudes and costs; the term enters the total with its weight
    blurred = (gt + torch.roll(gt, 1, 3) + torch.roll(gt, -1, 3)) / 3
    assert spectral_amplitude_loss(blurred, gt).item() > 0.01
    out["bwd_flow_px"] = None
    plain, _ = MultiStageLoss()(out, batch)
    total, terms = MultiStageLoss(spectral=7.0)(out, batch)
    assert terms["spectral"] == pytest.approx(expected, rel=1e-5)
    assert total.item() == pytest.approx(plain.item() + 7.0 * expected, rel=1e-5)
    good = {"model": {"name": "nafnet"}, "data": {"pack": "p"}, "train": {"iterations": 3}}
    assert load_config(base=good, overrides=["loss.spectral=20"]).loss.spectral == 20.0
    with pytest.raises(D2TurbError, match="loss.spectral"):
        load_config(base=good, overrides=["loss.spectral=-1"])


def test_native_loss_registry():
    from d2turb.models import create_model

    with torch.device("meta"):
        model = create_model("d2turb_lite")
    assert native_loss_name(model) == "l1"  # NAFNet backbone, registry entry
    assert native_loss_name(model, "psnr") == "psnr"
    with pytest.raises(D2TurbError, match="unknown native loss"):
        native_loss_name(model, "l3")


def _vgg_oracle(state: dict, x: torch.Tensor) -> list[torch.Tensor]:
    """VGG16 relu1_2..relu5_3 computed with plain functional ops from the state dict."""
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
    taps, feats, idx = {1, 3, 6, 9, 12}, [], 0  # conv counts after which a tap follows (0-based conv index)
    conv = 0
    for v in cfg:
        if v == "M":
            x = F.max_pool2d(x, 2)
            idx += 1
            continue
        x = F.relu(F.conv2d(x, state[f"features.{idx}.weight"], state[f"features.{idx}.bias"], padding=1))
        if conv in taps:
            feats.append(x)
        idx += 2
        conv += 1
    return feats


def test_vgg_term_with_tiny_random_vgg(tmp_path):
    from safetensors.torch import save_file

    from d2turb.eval.vgg import FeatureExtractor, imagenet_normalize

    torch.manual_seed(0)
    state = {k: v.contiguous() for k, v in FeatureExtractor("vgg").state_dict().items()}
    path = tmp_path / "vgg16.safetensors"
    save_file(state, str(path))
    out, batch = fake_batch(b=1, h=32, w=32)
    fa, fb = (
        _vgg_oracle(state, imagenet_normalize(out["restored"])),
        _vgg_oracle(state, imagenet_normalize(batch["gt"])),
    )
    expected_vgg = sum(((a - b) ** 2).mean() for a, b in zip(fa, fb)).item()
    photo = np.abs(out["restored"].numpy() - batch["gt"].numpy()).mean()
    assert PerceptualLoss.from_file(path)(out["restored"], batch["gt"]).item() == pytest.approx(expected_vgg, rel=1e-4)
    out["bwd_flow_px"] = None  # baseline: λ_photo L1 + λ_vgg VGG
    loss = build_loss({"vgg": 0.02, "vgg_weights": str(path)}, torch.nn.Identity())
    total, terms = loss(out, batch)
    assert terms["vgg"] == pytest.approx(expected_vgg, rel=1e-4)
    assert total.item() == pytest.approx(photo + 0.02 * expected_vgg, rel=1e-4)
    assert not any(p.requires_grad for p in loss.perceptual.parameters())  # frozen


def test_vgg_disabled_with_one_warning_when_weights_missing(capsys, tmp_path):
    import warnings

    with pytest.warns(UserWarning, match="vgg_weights not set") as caught:
        loss = build_loss({"vgg": 0.02, "vgg_weights": None}, torch.nn.Identity())
    assert len(caught) == 1 and capsys.readouterr().err == ""  # a warning, not a print
    assert loss.perceptual is None and loss.w_vgg == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_loss({"vgg": 0.0, "vgg_weights": None}, torch.nn.Identity())  # term off on purpose: no warning
    with pytest.raises(D2TurbError, match="no such file"):
        build_loss({"vgg": 0.02, "vgg_weights": str(tmp_path / "absent.pth")}, torch.nn.Identity())


# ------------------------------------------------------------------ configs
@pytest.mark.parametrize("path", sorted((REPO / "configs").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_config_builds_model_and_loss(path):
    from d2turb.models import create_model, list_models

    cfg = load_config(path)
    name, kwargs = cfg.model["name"], {k: v for k, v in cfg.model.items() if k != "name"}
    if name not in list_models():
        pytest.skip(f"{path.name}: model {name!r} is not registered yet")
    with torch.device("meta"):
        model = create_model(name, **kwargs)
    assert sum(p.numel() for p in model.parameters()) > 1e6
    loss = build_loss({**vars(cfg.loss), "vgg_weights": None}, model, warn=False)
    assert (loss.w_flow, loss.w_photo) == (5.0, 1.0)  # Sec. 3.3 weights
    # shipped-model recipes: no local VGG16 weights, so no perceptual term
    if path.stem.startswith(("d2turb_small", "nafnet_cpu", "gpu_nafnet")):
        assert cfg.loss.vgg == 0.0 or cfg.loss.vgg_weights is None
    else:
        assert cfg.loss.vgg == 0.02 and loss.w_deblur == (0.0 if "no_deblur" in path.stem else 1.0)
    if path.stem.startswith("d2turb_restormer"):
        injection = {"aspi": "aspi", "concat": "concat", "cascade": "none"}.get(path.stem.split("_")[-1], "aspi")
        assert (kwargs["backbone"], kwargs["injection"]) == ("restormer", injection)
        t = cfg.train
        assert (t.epochs, t.batch, t.lr, t.lr_min, cfg.data.patch) == (50, 8, 1e-4, 1e-6, 256)


def test_config_errors(tmp_path):
    import copy

    good = {"model": {"name": "d2turb_lite"}, "data": {"pairs": "x"}, "train": {"iterations": 3}}
    with pytest.raises(D2TurbError, match="unknown config key 'train.itrations'"):
        load_config(base=good, overrides=["train.itrations=5"])
    with pytest.raises(D2TurbError, match="exactly one of data.pairs"):
        load_config(base={**good, "data": {}})
    with pytest.raises(D2TurbError, match="exactly one of data.pairs"):
        load_config(base=good, overrides=["data.pack=p"])
    with pytest.raises(D2TurbError, match="exactly one of train.epochs"):
        load_config(base=good, overrides=["train.epochs=2"])
    with pytest.raises(D2TurbError, match="key=value"):
        load_config(base=good, overrides=["train.iterations"])
    for bad, match in (
        ("train.ema=1.5", "train.ema"),
        ("train.max_minutes=0", "train.max_minutes"),
        ("train.betas=[0.9]", "train.betas"),
        ("train.channels_last=1", "train.channels_last"),
        ("val.pack=p", None),  # valid: a pack can validate a pairs run
    ):
        if match is None:
            assert load_config(base=good, overrides=[bad]).val.pack == "p"
        else:
            with pytest.raises(D2TurbError, match=match):
                load_config(base=good, overrides=[bad])
    cfg = load_config(base=good, overrides=["train.lr=3e-4", "model.width=4", "model.backbone_cfg={width: 8}"])
    assert cfg.model["width"] == 4 and cfg.train.lr == 3e-4 and isinstance(cfg.train.lr, float)
    assert load_config(base=good, overrides=["model.backbone_cfg.depth=2"]).model == {
        "name": "d2turb_lite",
        "backbone_cfg": {"depth": 2},
    }  # model sections are free-form at every depth
    raw = {**copy.deepcopy(good), "data": {"clean": "some/folder"}}
    frozen = copy.deepcopy(raw)
    assert Config.from_dict(raw).data.clean == ["some/folder"] and raw == frozen  # validated, input untouched
    assert Config.from_dict(Config.from_dict(raw).to_dict()) == Config.from_dict(raw)  # round trip
    (tmp_path / "bad.yaml").write_text("model: [unclosed\n")
    with pytest.raises(D2TurbError, match="not valid YAML"):
        load_config(tmp_path / "bad.yaml")


# ------------------------------------------------------------------ training loop
def test_training_reduces_loss_on_fixed_batch(pairs, tmp_path):
    from d2turb.data import PairDataset

    trainer = Trainer(tiny_cfg(pairs, iterations=16, lr=3e-3), tmp_path / "run")
    fixed = torch.utils.data.default_collate([PairDataset(pairs)[i] for i in range(4)])

    def loss_on_fixed():
        with torch.no_grad():
            return trainer.loss(trainer.model(fixed["turb"]), fixed)

    before, terms_before = loss_on_fixed()
    summary = trainer.fit()
    after, terms_after = loss_on_fixed()
    assert summary["iteration"] == 16 and after < before
    assert terms_after["deblur"] < 0.7 * terms_before["deblur"] and terms_after["photo"] < 0.7 * terms_before["photo"]
    assert trainer.optimizer.param_groups[0]["lr"] == pytest.approx(1e-6)  # cosine annealed to lr_min
    from d2turb.models import load_pretrained

    reloaded = load_pretrained(tmp_path / "run" / "model.safetensors")
    assert all(torch.equal(a, b) for a, b in zip(reloaded.state_dict().values(), trainer.model.state_dict().values()))


def test_resume_equals_uninterrupted(pairs, tmp_path):
    # random 24² crops + flips: the data order and augmentation RNG must both come back on resume; so must the EMA
    from safetensors.torch import load_file

    cfg = tiny_cfg(pairs, iterations=5, ema=0.9, data={"patch": 24, "hflip": True, "vflip": True})
    outside = torch.get_rng_state()
    full = Trainer(cfg, tmp_path / "full")
    full.fit()
    assert torch.equal(torch.get_rng_state(), outside)  # the trainer never moves the caller's global RNG
    budget = tiny_cfg(pairs, iterations=5, ema=0.9, max_minutes=1e-9, data={"patch": 24, "hflip": True, "vflip": True})
    part = Trainer(budget, tmp_path / "part")
    assert part.fit()["stopped"] == "max_minutes"  # time budget spent: one step, checkpoint, clean exit
    assert part.iteration == 1 and (tmp_path / "part" / "model.safetensors").is_file()
    again = Trainer(cfg, tmp_path / "part", resume=True)
    assert again.iteration == 1
    assert again.fit(max_steps=2)["stopped"] == "max_steps"  # stops mid-epoch 1 (2 iterations per epoch)
    resumed = Trainer(cfg, tmp_path / "part", resume=True)
    assert resumed.iteration == 3
    assert resumed.fit()["stopped"] == "done"
    for (name, a), b in zip(full.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.equal(a, b), name
    for (name, a), b in zip(full.ema.model.state_dict().items(), resumed.ema.model.state_dict().values()):
        assert torch.equal(a, b), name
    shipped = load_file(str(tmp_path / "part" / "model.safetensors"))  # the EMA weights ship
    assert all(torch.equal(shipped[k], v) for k, v in resumed.ema.model.state_dict().items())
    logged = [json.loads(line) for line in (tmp_path / "part" / "log.jsonl").read_text().splitlines()]
    assert [r["iter"] for r in logged] == [1, 2, 3, 4, 5]


def test_epochs_bf16_autocast_channels_last_and_grad_clip(pairs, tmp_path):
    cfg = tiny_cfg(pairs, iterations=None, epochs=2, amp="bf16", grad_clip=0.5, channels_last=True)
    trainer = Trainer(cfg, tmp_path / "run")
    assert trainer.total == 2 * (8 // 4)  # epochs × drop-last batches per epoch
    conv = next(p for p in trainer.model.parameters() if p.ndim == 4 and p.shape[-1] > 1)
    assert conv.is_contiguous(memory_format=torch.channels_last) and not conv.is_contiguous()
    before = [p.detach().clone() for p in trainer.model.parameters()]
    summary = trainer.fit()
    assert summary["iteration"] == 4 and math.isfinite(summary["loss"])
    assert all(p.dtype == torch.float32 for p in trainer.model.parameters())  # autocast keeps fp32 master weights
    assert any(not torch.equal(a, b) for a, b in zip(before, trainer.model.parameters()))


def test_validation_writes_best_and_model(pairs, tmp_path):
    from d2turb.data import PairDataset

    cfg = tiny_cfg(pairs, iterations=4, val={"pairs": str(pairs), "every": 2, "max_images": 3, "crop": 16})
    Trainer(cfg, tmp_path / "run").fit()
    records = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    vals = [r for r in records if "val_psnr" in r]
    assert [r["iter"] for r in vals] == [2, 4] and all(5 < r["val_psnr"] < 60 and 0 < r["val_ssim"] <= 1 for r in vals)
    assert (tmp_path / "run" / "best.safetensors").is_file() and (tmp_path / "run" / "model.safetensors").is_file()
    # zero-flow end-point error and input PSNR, recomputed with numpy from the files (centre 16² crops)
    epe0, psnr_in = [], []
    for i in range(3):
        s = PairDataset(pairs)[i]
        flow, turb, gt = (s[k].double().numpy()[..., 8:24, 8:24] for k in ("bwd_flow_px", "turb", "gt"))
        epe0.append(np.sqrt((flow**2).sum(0)).mean())
        psnr_in.append(10 * np.log10(1.0 / ((turb - gt) ** 2).mean()))
    for r in vals:
        assert r["val_epe_zero"] == pytest.approx(np.mean(epe0), rel=1e-5)
        assert r["val_psnr_input"] == pytest.approx(np.mean(psnr_in), rel=1e-5)
        assert r["val_epe_weak"] == pytest.approx(r["val_epe"], rel=1e-9)  # every pair is in the weak bin


def test_interrupted_checkpoint_write_leaves_previous_intact(pairs, tmp_path, monkeypatch):
    trainer = Trainer(tiny_cfg(pairs, iterations=4), tmp_path / "run")
    trainer.fit(max_steps=1)
    ckpt = tmp_path / "run" / "last.pt"
    before = ckpt.read_bytes()
    real_save = torch.save

    def dying_save(obj, f, *a, **k):  # writes half a file, then the process "dies"
        real_save(obj, f, *a, **k)
        Path(f).write_bytes(Path(f).read_bytes()[:1000])
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", dying_save)
    with pytest.raises(KeyboardInterrupt):
        trainer.fit(max_steps=1)
    monkeypatch.undo()
    assert ckpt.read_bytes() == before
    assert sorted(p.name for p in (tmp_path / "run").iterdir() if p.name.startswith(".")) == []  # no temp files
    assert Trainer(tiny_cfg(pairs, iterations=4), tmp_path / "run").iteration == 1  # still resumable
    other = tiny_cfg(pairs, iterations=4)
    other.model["injection"] = "concat"
    with pytest.raises(D2TurbError, match="checkpoint is for model"):
        Trainer(other, tmp_path / "run")
    ckpt.write_bytes(before[:500])  # a truncated checkpoint (e.g. copied by hand) is a one-line error
    with pytest.raises(D2TurbError, match="unreadable checkpoint"):
        Trainer(tiny_cfg(pairs, iterations=4), tmp_path / "run")


def test_on_the_fly_synthesis_training(tmp_path, astronaut):
    from d2turb.io import write_image

    (tmp_path / "clean").mkdir()
    write_image(tmp_path / "clean" / "a.png", astronaut[0, :, :64, :64])
    base = {
        "model": TINY_MODEL,
        "data": {
            "clean": [str(tmp_path / "clean")],
            "patch": 32,
            "num_workers": 0,
            "on_the_fly": {"depth": "none", "length": 4, "bins": ["strong"]},
        },
        "train": {"iterations": 2, "batch": 2, "device": "cpu"},
        "loss": {"vgg": 0.0},
        "log": {"progress": False},
    }
    trainer = Trainer(load_config(base=base), tmp_path / "run")
    batch = trainer.data.to_device(next(iter(trainer.data.loader)))
    assert batch["turb"].shape == (2, 3, 32, 32) and batch["bwd_flow_px"].shape == (2, 2, 32, 32)
    assert float(batch["dr0"].min()) >= 3.75 and not torch.equal(batch["turb"], batch["gt"])
    summary = trainer.fit()
    assert summary["iteration"] == 2 and math.isfinite(summary["loss"])


# ------------------------------------------------------------------ DDP
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ddp_two_processes_equal_one_process(pairs, tmp_path):
    """Two gloo processes with 2 samples each = one process with the batch of 4 (EMA included); so is validation on
    3 images shared unevenly (2 + 1) between the ranks."""
    import yaml
    from safetensors.torch import load_file

    cfg = tiny_cfg(pairs, iterations=2, batch=4, ema=0.5, val={"pairs": str(pairs), "every": 2, "max_images": 3})
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    cmd = [sys.executable, "-m", "d2turb", "train", "--config", str(tmp_path / "cfg.yaml"), "--out", str(tmp_path)]
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env.update(OMP_NUM_THREADS="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(_free_port()))
    procs = [
        subprocess.Popen(
            cmd[:-1] + [str(tmp_path / "ddp")],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**env, "RANK": str(r), "LOCAL_RANK": str(r), "WORLD_SIZE": "2"},
        )
        for r in range(2)
    ]
    single = Trainer(cfg, tmp_path / "single")  # meanwhile, the one-process run in this process
    init = {k: v.clone() for k, v in single.model.state_dict().items()}
    single.fit()
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1].decode()[-2000:] for o in outs]
    assert b"trained 2/2" in outs[0][0] and outs[1][0] == b""  # only rank 0 reports
    a, b = single.ema.model.state_dict(), load_file(str(tmp_path / "ddp" / "model.safetensors"))
    assert any(not torch.equal(init[k], a[k]) for k in a)  # training moved the weights
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-5, msg=k)
    vals = [
        next(json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if "val_psnr" in line)
        for run in (tmp_path / "single", tmp_path / "ddp")
    ]
    assert vals[0].keys() == vals[1].keys() and "val_epe_weak" in vals[0]
    for k, v in vals[0].items():  # the input's metrics exactly; the model's to the weights' float tolerance
        assert vals[1][k] == pytest.approx(v, rel=1e-9 if "input" in k or "zero" in k else 1e-4), k


@pytest.mark.slow
def test_ddp_stop_right_after_a_checkpoint_does_not_hang(pairs, tmp_path):
    """A time budget spent at a checkpoint step: no rank saves again (rank 1 used to wait in the final save's
    collective while rank 0 had left: a hang)."""
    import yaml

    cfg = tiny_cfg(pairs, iterations=2, batch=4, max_minutes=1e-9).to_dict()
    cfg["checkpoint"]["every"] = 1
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    cmd = [
        sys.executable,
        "-m",
        "d2turb",
        "train",
        "--config",
        str(tmp_path / "cfg.yaml"),
        "--out",
        str(tmp_path / "o"),
    ]
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env.update(OMP_NUM_THREADS="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(_free_port()))
    procs = [
        subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**env, "RANK": str(r), "LOCAL_RANK": str(r), "WORLD_SIZE": "2"},
        )
        for r in range(2)
    ]
    try:
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert all(p.returncode == 0 for p in procs), [o[1].decode()[-2000:] for o in outs]
    assert b"trained 1/2" in outs[0][0] and b"stopped: max_minutes" in outs[0][0]


# ------------------------------------------------------------------ CLI
def test_cli_one_line_errors(capsys, tmp_path, pairs):
    from d2turb.cli import main

    assert main(["train", "--config", str(tmp_path / "missing.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: config file not found: {tmp_path / 'missing.yaml'}"]
    (tmp_path / "c.yaml").write_text(
        f"model: {{name: d2turb_lite}}\ndata: {{pairs: {pairs}}}\ntrain: {{iterations: 1}}\n"
    )
    assert main(["train", "--config", str(tmp_path / "c.yaml"), "--set", "loss.lambda_flow=3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: unknown config key 'loss.lambda_flow'")
    assert (
        main(
            [
                "train",
                "--config",
                str(tmp_path / "c.yaml"),
                "--out",
                str(tmp_path / "r"),
                "--resume",
                "--set",
                "train.device=cpu",
            ]
        )
        == 2
    )
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("error: --resume: no checkpoint")


@pytest.mark.slow
def test_diverging_training_stops_in_one_line_not_a_segfault(tmp_path):
    """A learning rate that makes the loss inf/NaN: before, the NaN flow reached grid_sample's backward and the
    process died by SIGSEGV with status.json still "running"."""
    config = tiny_config(tmp_path)
    run = tmp_path / "run"
    proc = run_d2turb("train", "--config", config, "--out", run, "--set", "train.lr=1e6")
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    line = one_error_line(proc.stderr, "loss became non-finite at iteration", "train.lr")
    iteration = int(line.split("at iteration ")[1].split()[0])
    status = json.loads((run / "status.json").read_text())
    assert status["state"] == "failed" and "non-finite" in status["error"]
    logged = [json.loads(s) for s in (run / "log.jsonl").read_text().splitlines()]
    assert [r["iter"] for r in logged] == list(range(1, iteration))  # the failed step is not logged
    assert all(np.isfinite(r["loss"]) for r in logged)


@pytest.mark.parametrize(
    "setting, words",
    [
        ("train.lr_min=.inf", ["train.lr_min", "finite"]),
        ("train.lr=.nan", ["train.lr", "finite"]),
        ("train.lr=0", ["train.lr", "positive"]),
        ("train.lr_min=1e-2", ["train.lr_min", "train.lr"]),  # above lr: the schedule would rise
        ("train.seed=1.5", ["train.seed", "integer"]),
        ("train.seed=abc", ["train.seed", "integer"]),
        ("train.seed=-1", ["train.seed", "2**63"]),
        ("val.seed=1.5", ["val.seed", "integer"]),
        ("data.patch=100000", ["data.patch", "4096"]),
    ],
)
def test_impossible_training_settings_are_one_line(setting, words, tmp_path, capsys):
    config = tiny_config(tmp_path)
    rc, _, err = run_cli(capsys, ["train", "--config", str(config), "--out", str(tmp_path / "run"), "--set", setting])
    assert rc == 2
    one_error_line(err, *words)
    assert not (tmp_path / "run").exists()


def test_train_removes_the_temp_checkpoint_a_killed_run_left(tmp_path, capsys):
    config = tiny_config(tmp_path, iterations=2)
    run = tmp_path / "run"
    run.mkdir()
    stale = run / f".last.pt.{dead_pid()}-0123abcd.tmp.pt"
    stale.write_bytes(b"\0" * 1000)
    live = run / f".last.pt.{os.getppid()}-0123abcd.tmp.pt"  # a process that still runs may be writing it
    live.write_bytes(b"")
    assert main(["train", "--config", str(config), "--out", str(run)]) == 0
    capsys.readouterr()
    assert not stale.exists() and live.exists()


def test_resume_after_a_kill_does_not_repeat_log_lines(tmp_path):
    """A kill -9 between checkpoints leaves log lines of iterations the checkpoint does not hold; the resumed
    run trains those iterations again, and the log must say each once (the state of such a kill is made
    exactly: the checkpoint of iteration 2 put back after iterations 3 and 4 were logged)."""
    import shutil

    from d2turb.train import Trainer, load_config

    cfg = load_config(tiny_config(tmp_path, iterations=6))
    cfg.val.every = 1000
    run = tmp_path / "run"
    trainer = Trainer(cfg, run)
    trainer.fit(max_steps=2)
    shutil.copy(run / "last.pt", tmp_path / "at2.pt")
    trainer.fit(max_steps=2)
    shutil.copy(tmp_path / "at2.pt", run / "last.pt")  # what the kill left: log to 4, checkpoint at 2
    assert [json.loads(s)["iter"] for s in (run / "log.jsonl").read_text().splitlines()] == [1, 2, 3, 4]
    trainer = Trainer(cfg, run)
    assert trainer.iteration == 2
    trainer.fit()
    assert [json.loads(s)["iter"] for s in (run / "log.jsonl").read_text().splitlines()] == [1, 2, 3, 4, 5, 6]
