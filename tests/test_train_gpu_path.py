"""The GPU path of d2turb.train, run on CPU with tiny models: training from an in-memory pack with pack validation
(PSNR/SSIM and flow end-point error vs zero flow), EMA against a hand-computed average, --init-from (file and name,
strict, mismatched config refused, resume wins; a plain NAFNet file initialises D²Turb's backbone), torch.compile,
SIGTERM, detached training and --status."""

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train import TINY_MODEL, make_pairs, tiny_cfg

from d2turb.errors import D2TurbError
from d2turb.train import Trainer, load_config, read_status


@pytest.fixture(autouse=True)
def _one_thread(_torch_threads):
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def pairs(tmp_path_factory) -> Path:
    return make_pairs(tmp_path_factory.mktemp("pairs"))


@pytest.fixture(scope="module")
def pack(tmp_path_factory) -> Path:
    from d2turb.data.pack import make_pack
    from d2turb.io import write_image

    root = tmp_path_factory.mktemp("clean")
    g = torch.Generator().manual_seed(0)
    for folder, n in (("urban100", 3), ("set14", 2), ("bsd100", 1)):
        (root / folder).mkdir()
        for i in range(n):
            image = torch.nn.functional.interpolate(torch.rand(1, 3, 6, 6, generator=g), size=(40, 48), mode="bicubic")
            write_image(root / folder / f"{i}.png", image[0].clamp(0, 1))
    out = tmp_path_factory.mktemp("packs") / "pack"
    make_pack([root], out, patch=32)
    return out


def pack_cfg(pack: Path, **train):
    return load_config(
        base={
            "model": TINY_MODEL,
            "data": {"pack": str(pack), "patch": 32, "on_the_fly": {"depth": "prior", "length": 4}},
            "train": {"iterations": 2, "batch": 2, "device": "cpu", **train},
            "loss": {"vgg": 0.0},
            "val": {"pack": str(pack), "every": 2, "crop": 32, "seed": 5},
            "log": {"every": 1, "progress": False},
        }
    )


def test_training_from_a_pack_with_pack_validation(pack, tmp_path):
    trainer = Trainer(pack_cfg(pack), tmp_path / "run")
    batch = trainer.data.to_device(next(iter(trainer.data.loader)))
    assert batch["turb"].shape == (2, 3, 32, 32) and batch["bwd_flow_px"].shape == (2, 2, 32, 32)
    assert batch["depth"].shape == (2, 1, 32, 32) and not torch.equal(batch["depth"], torch.ones_like(batch["depth"]))
    # validation: 2 val images × 3 bins, each pair once, fixed (a second trainer synthesises the same set)
    val = trainer.val_loader
    assert sum(len(b["bin"]) for b in val) == 6 and sorted(int(b) for v in val for b in v["bin"]) == [0, 0, 1, 1, 2, 2]
    twin = trainer.validation.pack_batches()  # synthesised again from the same seeds
    assert all(torch.equal(a["turb"], b["turb"]) for a, b in zip(val, twin))
    flows = [v["bwd_flow_px"][i].double().numpy() for v in val for i in range(len(v["bin"]))]
    epe_zero = np.mean([np.sqrt((f**2).sum(0)).mean() for f in flows])  # mean ‖V‖₂ over pixels, then pairs
    summary = trainer.fit()
    assert summary["stopped"] == "done" and summary["iteration"] == 2
    records = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    record = next(r for r in records if "val_psnr" in r)
    assert record["val_epe_zero"] == pytest.approx(epe_zero, rel=1e-6) and record["val_epe"] > 0
    for key in ("psnr", "ssim", "psnr_input", "ssim_input", "epe", "epe_zero"):
        assert all(f"val_{key}_{b}" in record for b in ("weak", "medium", "strong")), key
    status = read_status(tmp_path / "run")
    assert status["state"] == "finished" and status["iteration"] == 2 and status["val"]["iter"] == 2
    assert (tmp_path / "run" / "best.safetensors").is_file()


def test_ema_matches_hand_computed_average_of_two_steps(pairs, tmp_path):
    trainer = Trainer(tiny_cfg(pairs, iterations=4, ema=0.95), tmp_path / "run")

    def weights():
        return {k: v.detach().double().clone() for k, v in trainer.model.state_dict().items()}

    theta = [weights()]
    for _ in range(2):
        trainer.fit(max_steps=1)
        theta.append(weights())
    b0, b1 = min(0.95, 1 / 10), min(0.95, 2 / 11)  # β_t = min(β, (1 + t) / (10 + t))
    for k, averaged in trainer.ema.model.state_dict().items():
        ema1 = b0 * theta[0][k] + (1 - b0) * theta[1][k]
        expected = b1 * ema1 + (1 - b1) * theta[2][k]
        torch.testing.assert_close(averaged.double(), expected, rtol=1e-6, atol=1e-8, msg=k)
    assert any(not torch.equal(theta[2][k].float(), v) for k, v in trainer.ema.model.state_dict().items())


def test_init_from_file_and_name(pairs, tmp_path, monkeypatch):
    from d2turb.models import create_model, save_pretrained

    name, kwargs = TINY_MODEL["name"], {k: v for k, v in TINY_MODEL.items() if k != "name"}
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1234)  # weights unlike the run's own seeded init
        source = create_model(name, **kwargs)
    path = save_pretrained(source, tmp_path / "weights" / "tiny-test.safetensors")
    trainer = Trainer(tiny_cfg(pairs, init_from=str(path), ema=0.9), tmp_path / "run")
    expected = source.state_dict()
    assert all(torch.equal(v, expected[k]) for k, v in trainer.model.state_dict().items())
    assert all(torch.equal(v, expected[k]) for k, v in trainer.ema.model.state_dict().items())
    assert trainer.iteration == 0 and not trainer.optimizer.state  # weights only
    trainer.fit(max_steps=1)
    monkeypatch.setenv("D2TURB_WEIGHTS_DIR", str(tmp_path / "weights"))  # a name resolves like restore's
    by_name = Trainer(tiny_cfg(pairs, init_from="tiny-test"), tmp_path / "by_name")
    assert all(torch.equal(v, expected[k]) for k, v in by_name.model.state_dict().items())
    resumed = Trainer(tiny_cfg(pairs, init_from="tiny-test", ema=0.9), tmp_path / "run")  # last.pt wins
    assert resumed.iteration == 1 and all(
        torch.equal(v, trainer.model.state_dict()[k]) for k, v in resumed.model.state_dict().items()
    )
    wider = create_model(name, **{**kwargs, "backbone_cfg": {**kwargs["backbone_cfg"], "width": 16}})
    other = save_pretrained(wider, tmp_path / "wider.safetensors")
    with pytest.raises(D2TurbError, match="weights are for model"):
        Trainer(tiny_cfg(pairs, init_from=str(other)), tmp_path / "mismatch")
    with pytest.raises(D2TurbError, match="not found"):
        Trainer(tiny_cfg(pairs, init_from="no-such-weights"), tmp_path / "missing")


def test_init_from_a_plain_backbone_loads_the_backbone_and_starts_as_it(pairs, tmp_path):
    """A D²Turb run started from a standalone NAFNet file (the shipped models' kind) takes its backbone strictly and
    keeps its own rectifier; with the zero flow head the model restores exactly as the NAFNet file does (the oracle:
    the file loaded on its own), and a backbone of another config is refused."""
    from d2turb.models import create_model, load_pretrained, save_pretrained

    backbone_cfg = TINY_MODEL["backbone_cfg"]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(99)
        nafnet = create_model("nafnet", **backbone_cfg)
        for p in nafnet.parameters():  # trained-looking weights: NAFNet's gains start at zero (identity)
            p.data.add_(0.05 * torch.randn_like(p))
    path = save_pretrained(nafnet, tmp_path / "nafnet.safetensors")
    trainer = Trainer(tiny_cfg(pairs, init_from=str(path), ema=0.9), tmp_path / "run")
    expected = nafnet.backbone.state_dict()
    assert all(torch.equal(v, expected[k]) for k, v in trainer.model.backbone.state_dict().items())
    assert all(torch.equal(v, expected[k]) for k, v in trainer.ema.model.backbone.state_dict().items())
    x = torch.rand(2, 3, 32, 64, generator=torch.Generator().manual_seed(3))  # sides of D²Turb's multiple: no pad
    with torch.no_grad():
        out, ref = trainer.model.eval()(x), load_pretrained(path)(x)["restored"]
    assert torch.equal(out["bwd_flow_px"], torch.zeros_like(out["bwd_flow_px"]))
    torch.testing.assert_close(out["restored"], ref, atol=1e-6, rtol=0)
    assert (ref - x).abs().mean() > 1e-3  # the weights do something: the comparison is not identity against identity
    narrower = save_pretrained(create_model("nafnet", **{**backbone_cfg, "width": 4}), tmp_path / "n4.safetensors")
    with pytest.raises(D2TurbError, match="or its backbone"):
        Trainer(tiny_cfg(pairs, init_from=str(narrower)), tmp_path / "mismatch")


@pytest.mark.slow
def test_compile_matches_eager_and_checkpoints_plain_names(pairs, tmp_path):
    plain = Trainer(tiny_cfg(pairs, iterations=2), tmp_path / "plain")
    plain.fit()
    compiled = Trainer(tiny_cfg(pairs, iterations=2, compile="eager"), tmp_path / "compiled")
    compiled.fit()  # the "eager" backend traces with dynamo but runs the same kernels
    state = torch.load(tmp_path / "compiled" / "last.pt", weights_only=True)["model"]
    assert list(state) == list(plain.model.state_dict())  # no _orig_mod. prefixes
    for k, v in plain.model.state_dict().items():
        torch.testing.assert_close(state[k], v, rtol=1e-5, atol=1e-6, msg=k)


def test_sigterm_checkpoints_and_stops(pairs, tmp_path):
    trainer = Trainer(tiny_cfg(pairs, iterations=4), tmp_path / "run")
    real_step = trainer.train_step

    def step_then_terminated(batch):
        out = real_step(batch)
        os.kill(os.getpid(), signal.SIGTERM)  # e.g. the host's job limit
        return out

    trainer.train_step = step_then_terminated
    summary = trainer.fit(handle_sigterm=True)
    assert summary["stopped"] == "signal" and summary["iteration"] == 1
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handler removed again
    status = read_status(tmp_path / "run")
    assert (status["state"], status["reason"], status["checkpoint_iteration"]) == ("stopped", "signal", 1)
    assert Trainer(tiny_cfg(pairs, iterations=4), tmp_path / "run").iteration == 1


@pytest.mark.slow
def test_detached_training_status_and_guard(pairs, tmp_path, capsys, monkeypatch):
    import yaml

    from d2turb.cli import main
    from d2turb.models import create_model, save_pretrained

    cfg = tiny_cfg(pairs, iterations=3).to_dict()
    cfg["loss"]["vgg"] = 0.02  # no vgg_weights: one warning line in the log
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    name, kwargs = TINY_MODEL["name"], {k: v for k, v in TINY_MODEL.items() if k != "name"}
    weights = save_pretrained(create_model(name, **kwargs), tmp_path / "init.safetensors")
    run = tmp_path / "run"
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    config = ["train", "--config", str(tmp_path / "cfg.yaml"), "--out", str(run)]
    assert main(config + ["--detach", "--init-from", str(weights)]) == 0
    pid = int(capsys.readouterr().out.split("pid ")[1].split(",")[0])
    deadline = time.time() + 240
    while time.time() < deadline:  # a background process in its own session (here, a child of this one)
        if os.waitpid(pid, os.WNOHANG)[0] == pid:
            break
        time.sleep(0.05)
    logged = (run / "train.log").read_text()
    assert "trained 3/3" in logged, logged[-2000:]
    assert "warning: loss.vgg_weights not set" in logged and "initialised from" in logged
    assert read_status(run)["state"] == "finished"
    assert main(["train", "--status", str(run)]) == 0
    out = capsys.readouterr().out
    assert "finished" in out and "iteration 3/3" in out
    (run / "status.json").write_text(  # a live training of this folder: a second one is refused
        json.dumps({"state": "running", "pid": os.getpid(), "host": __import__("socket").gethostname()})
    )
    assert main(config) == 2
    assert "is being trained by process" in capsys.readouterr().err
    assert main(["train", "--status", str(tmp_path)]) == 2  # not a run folder: one-line error
