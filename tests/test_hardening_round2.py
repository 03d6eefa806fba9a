"""Hostile input at the command line, round 2 (issue 25): no crash by signal, nothing read outside a dataset,
no user file overwritten, one `error:` line instead of a traceback, no quiet wrong output."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from test_hardening import error_lines, one_error_line, run_cli
from test_train import TINY_MODEL

from d2turb.cli import main

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
ROOT = Path(__file__).resolve().parents[1]
ENV["PYTHONPATH"] = str(ROOT / "src") + os.pathsep + ENV.get("PYTHONPATH", "")


# ----------------------------------------------------------------------------------------------- helpers
def rgb(path: Path, h: int = 24, w: int = 32, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)).save(path)
    return path


def make_dataset_args(clean, out, *extra):
    args = ["make-dataset", "--clean", str(clean), "--out", str(out), "--pairs", "2", "--patch", "16", "--batch", "2"]
    return [*args, "--depth", "none", "--device", "cpu", "--no-progress", *extra]


def run_d2turb(*args, timeout: float = 300, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "d2turb", *map(str, args)],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,
    )


# ------------------------------------------------------------------------------- 1. no crash by a signal
@pytest.mark.parametrize("size", [(3, 200), (5, 128)])
def test_simulate_a_few_pixels_high_exits_normally(size, tmp_path):
    image = rgb(tmp_path / "strip.png", *size)
    proc = run_d2turb("simulate", image, "--out", tmp_path / "out")
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])  # a signal would be negative
    assert Image.open(tmp_path / "out" / "strip_turb.png").size == (size[1], size[0])


def test_every_fft_of_the_simulator_gets_a_contiguous_tensor(tmp_path, monkeypatch, capsys):
    """The abort came from torch.fft.fft2 on the permuted view einsum returns: every FFT input in d2turb.sim
    must be contiguous (checked on the calls themselves, in simulate and simulate-video)."""
    seen = []
    for name in ("fft2", "ifft2", "rfft2", "irfft2", "fftn", "ifftn", "rfftn", "irfftn"):
        original = getattr(torch.fft, name)

        def spy(x, *args, _original=original, _name=name, **kwargs):
            seen.append((_name, tuple(x.shape), x.is_contiguous()))
            return _original(x, *args, **kwargs)

        monkeypatch.setattr(torch.fft, name, spy)
    image = rgb(tmp_path / "strip.png", 3, 200)
    assert main(["simulate", str(image), "--out", str(tmp_path / "a")]) == 0
    image = rgb(tmp_path / "b.png", 24, 40)
    assert main(["simulate", str(image), str(tmp_path / "strip.png"), "--out", str(tmp_path / "b")]) == 0
    args = ["simulate-video", str(image), "--out", str(tmp_path / "v"), "--frames", "2", "--no-mp4"]
    assert main(args) == 0
    capsys.readouterr()
    assert seen and all(contiguous for _, _, contiguous in seen), [s for s in seen if not s[2]]


# ------------------------------------------------------------------------------------------ 2. training


def tiny_pairs(root: Path, n: int = 4, size: int = 32, split: str = "train") -> Path:
    """A make-dataset folder written by hand from its documented layout (docs/data.md): random images, zero flow."""
    rng = np.random.default_rng(0)
    lines = []
    for i in range(n):
        sid = f"{i:07d}"
        for kind in ("turb", "tilt", "gt"):
            rgb(root / kind / f"{sid}.png", size, size, seed=i)
        (root / "depth").mkdir(exist_ok=True)
        Image.fromarray(rng.integers(0, 65535, (size, size), dtype=np.uint16)).save(root / "depth" / f"{sid}.png")
        (root / "flow").mkdir(exist_ok=True)
        np.save(root / "flow" / f"{sid}.npy", np.zeros((2, size, size), np.float16))
        lines.append(json.dumps({"id": sid, "index": i, "dr0": 2.0, "bin": "weak", "split": split}))
    config = {"version": 1, "pairs": n, "patch": size, "split": split, "bin_ranges": {"weak": [1.0, 2.25]}}
    (root / "dataset.json").write_text(json.dumps(config))
    (root / "meta.jsonl").write_text("\n".join(lines) + "\n")
    return root


def tiny_config(tmp_path: Path, **train) -> Path:
    import yaml

    cfg = {
        "model": TINY_MODEL,
        "data": {"pairs": str(tiny_pairs(tmp_path / "pairs")), "patch": 32, "num_workers": 0, "hflip": False},
        "train": {"iterations": 6, "batch": 2, "lr": 1e-3, "device": "cpu", **train},
        "loss": {"vgg": 0.0},
        "log": {"every": 1, "progress": False},
        "checkpoint": {"every": 1000},
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


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


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_train_removes_the_temp_checkpoint_a_killed_run_left(tmp_path, capsys):
    config = tiny_config(tmp_path, iterations=2)
    run = tmp_path / "run"
    run.mkdir()
    stale = run / f".last.pt.{_dead_pid()}-0123abcd.tmp.pt"
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


# ------------------------------------------------------------------------ 3. nothing read outside a dataset
def _dataset_with_meta(root: Path, records: list[dict]) -> Path:
    tiny_pairs(root, n=2, size=16, split="test")
    (root / "meta.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return root


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


@pytest.mark.parametrize("bad_id", ["/etc/passwd", "a/b", "..", ".hidden", "", 7, None])
def test_meta_ids_must_be_plain_names(bad_id, tmp_path):
    from d2turb.data import PairDataset
    from d2turb.errors import D2TurbError

    root = tiny_pairs(tmp_path / "ds", n=1, size=16)
    (root / "meta.jsonl").write_text(json.dumps({"id": bad_id, "index": 0, "dr0": 2.0, "bin": "weak"}) + "\n")
    with pytest.raises(D2TurbError, match="meta.jsonl line 1"):
        PairDataset(root)


def test_a_pack_entry_that_leaves_the_pack_is_refused(tmp_path):
    from d2turb.data.pack import make_pack, read_pack
    from d2turb.errors import D2TurbError

    for i in range(2):
        rgb(tmp_path / "clean" / "folder" / f"{i}.png", 64, 64, seed=i)
    make_pack([tmp_path / "clean" / "folder"], tmp_path / "pack", patch=32, progress=False)
    manifest = json.loads((tmp_path / "pack" / "pack.json").read_text())
    manifest["images"][0]["file"] = "../clean/folder/0.png"
    (tmp_path / "pack" / "pack.json").write_text(json.dumps(manifest))
    with pytest.raises(D2TurbError, match=r"pack\.json.*\.\./clean/folder/0\.png"):
        read_pack(tmp_path / "pack", verify=False)


# -------------------------------------------------------------------------- 4. no user file overwritten
def test_simulate_into_its_input_folder_is_refused(tmp_path, capsys):
    folder = tmp_path / "photos"
    rgb(folder / "a.png", 24, 32)
    mine = rgb(folder / "a_tilt.png", 24, 32, seed=5)  # the user's own file, named like an output
    before = mine.read_bytes()
    for argv in (
        ["simulate", str(folder), "--out", str(folder)],
        ["simulate", str(folder / "a.png"), "--out", str(folder)],
        ["simulate", str(folder / "a.png"), "--out", str(folder / "." / "")],
    ):
        rc, _, err = run_cli(capsys, argv)
        assert rc == 2
        one_error_line(err, "--out", "input")
        assert mine.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == ["a.png", "a_tilt.png"]
    rc, _, err = run_cli(capsys, ["restore", str(folder), "--weights", "input", "--out", str(folder)])
    assert rc == 2
    one_error_line(err, "--out", "input")
    assert main(["simulate", str(folder / "a.png"), "--out", str(tmp_path / "out")]) == 0  # elsewhere: fine
    capsys.readouterr()


def test_simulate_video_rerun_with_fewer_frames_leaves_a_consistent_folder(tmp_path, capsys):
    image = rgb(tmp_path / "a.png", 24, 32)
    out = tmp_path / "clip"
    base = ["simulate-video", str(image), "--out", str(out), "--no-mp4"]
    assert main([*base, "--frames", "4", "--save-tilt", "--save-flow"]) == 0
    assert len(list((out / "turb").iterdir())) == 4
    assert main([*base, "--frames", "2"]) == 0
    capsys.readouterr()
    meta = json.loads((out / "meta.json").read_text())
    assert meta["frames"] == 2
    assert sorted(p.name for p in (out / "turb").iterdir()) == ["000000.png", "000001.png"]
    for kind in ("tilt", "flow"):  # not asked for this time: the earlier run's frames would not match turb/
        assert not (out / kind).exists() or not any((out / kind).iterdir())


def test_two_make_dataset_runs_into_one_folder(tmp_path, capsys):
    """The second run is refused in one line naming the first one's process; a lock left by a killed run
    (its process gone) is taken over."""
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    out = tmp_path / "ds"
    first = subprocess.Popen(
        [sys.executable, "-m", "d2turb", *make_dataset_args(clean, out, "--pairs", "4000")],
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and first.poll() is None and not (out / "dataset.json").is_file():
            time.sleep(0.01)
        assert first.poll() is None, "the first run ended before the second started"
        rc, _, err = run_cli(capsys, make_dataset_args(clean, out))
        assert first.poll() is None, "the first run ended before the second was refused"
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    assert rc == 2
    one_error_line(err, str(out), f"process {first.pid}")
    assert first.returncode == -signal.SIGKILL
    # the killed run's lock stays (docs/cli.md: DIR/.d2turb.lock); the rest is cleared to start a small dataset
    for p in out.iterdir():
        if p.name != ".d2turb.lock":
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    assert str(first.pid) in (out / ".d2turb.lock").read_text()
    rc, _, err = run_cli(capsys, make_dataset_args(clean, out))  # the dead process's lock is taken over
    assert rc == 0, err
    assert main(["check-dataset", str(out)]) == 0
    assert not (out / ".d2turb.lock").exists()  # released at the end
    capsys.readouterr()


# ------------------------------------------------------------------------------- 5. damaged dataset files
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


def test_evaluate_epe_skips_a_flow_of_the_wrong_size(tmp_path, capsys):
    root = tiny_pairs(tmp_path / "ds", n=3, size=16, split="test")
    np.save(root / "flow" / "0000001.npy", np.zeros((2, 8, 8), np.float16))
    out = tmp_path / "o"
    rc, _, err = run_cli(
        capsys, ["evaluate", "--data", str(root), "--weights", "input", "--metrics", "epe", "--out", str(out)]
    )
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 1 and "0000001" in lines[0] and "flow" in lines[0] and "Traceback" not in err
    results = json.loads((out / "results.json").read_text())
    assert results["samples_evaluated"] == 2 and [s["id"] for s in results["skipped"]] == ["0000001"]
    assert results["table"]["input"]["epe"]["avg"] == 0.0  # zero flow against zero flow


# ----------------------------------------------------------------------------------------- 6. make-pack
@pytest.mark.parametrize(
    "option, value", [("--max-mib", "nan"), ("--max-mib", "inf"), ("--max-mib", "-1"), ("--max-side", "-5")]
)
def test_make_pack_limits_are_checked(option, value, tmp_path, capsys):
    rgb(tmp_path / "clean" / "folder" / "a.png", 64, 64)
    argv = ["make-pack", "--clean", str(tmp_path / "clean" / "folder"), "--out", str(tmp_path / "pack")]
    rc, _, err = run_cli(capsys, [*argv, "--patch", "32", "--no-progress", option, value])
    assert rc == 2
    one_error_line(err, option, value)
    assert not (tmp_path / "pack").exists()


# ------------------------------------------------------------------------------- 7. float images, quietly
def _float_tiff(path: Path, values: np.ndarray) -> Path:
    Image.fromarray(values.astype(np.float32), mode="F").save(path)
    return path


@pytest.mark.parametrize(
    "name, words",
    [("scale", ["0 to 1000", "[0, 1]"]), ("inf", ["NaN or infinite"]), ("nan", ["NaN or infinite"])],
)
def test_float_tiff_out_of_range_or_non_finite_is_refused(name, words, tmp_path, capsys):
    values = np.linspace(0, 1, 24 * 32).reshape(24, 32)
    if name == "scale":
        values = values * 1000
    else:
        values[3, 4] = np.inf if name == "inf" else np.nan
    image = _float_tiff(tmp_path / f"{name}.tif", values)
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o")])
    assert rc == 2
    one_error_line(err, f"{name}.tif", *words)
    assert not (tmp_path / "o").exists()


def test_float_tiff_in_range_is_read_as_is(tmp_path):
    from d2turb.io import read_image

    values = np.linspace(0, 1, 24 * 32).reshape(24, 32).astype(np.float32)
    image = read_image(_float_tiff(tmp_path / "ok.tif", values))
    assert image.shape == (3, 24, 32) and torch.equal(image[1], torch.from_numpy(values))


# --------------------------------------------------------------------------------------- 8. long names
def test_outputs_with_the_longest_legal_names_are_written(tmp_path, capsys):
    stem = "é" + "x" * 234  # 236 bytes: NAME_meta.json is 250 bytes, within the 255 a file name may have
    image = rgb(tmp_path / "in" / f"{stem}.png", 24, 32)
    out = tmp_path / "out"
    out.mkdir()
    leftover = out / f".{stem[:200]}.png.{_dead_pid()}-deadbeef.tmp.png"  # a cut temp name of a killed run
    leftover.write_bytes(b"")
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(out)])
    assert rc == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{stem}_{k}" for k in ("turb.png", "tilt.png", "meta.json"))
    assert Image.open(out / f"{stem}_turb.png").size == (32, 24)


def test_temp_names_fit_whenever_the_name_does():
    from d2turb.io import temp_name

    for name in ("a.png", "x" * 251 + ".png", "é" * 125 + ".json", "y" * 255, "z" * 248 + ".tar.gz"):
        assert len(name.encode()) <= 255
        tmp = temp_name(name, f"{2**22}-0123abcd")
        assert (
            len(tmp.encode()) <= 255
            and tmp.startswith(".")
            and tmp.endswith(f".{2**22}-0123abcd.tmp{Path(name).suffix}")
        )
        tmp.encode().decode()  # cut at a character boundary
    # a name that is not UTF-8 (raw bytes, surrogate-escaped by Python) is counted and kept in bytes (issue 37)
    for raw in (b"\xff\xfe.png", b"\xe9" * 251 + b".png"):
        tmp = temp_name(os.fsdecode(raw), "1-0123abcd")
        assert len(os.fsencode(tmp)) <= 255 and os.fsencode(tmp).startswith(b"." + raw[:8])


# ------------------------------------------------------------------------------------ 9. broken links
@pytest.mark.skipif(os.name != "posix", reason="symbolic links")
@pytest.mark.parametrize("command", ["simulate", "restore"])
def test_dangling_and_looping_links_in_a_folder_are_reported(command, tmp_path, capsys):
    folder = tmp_path / "in"
    rgb(folder / "a.png", 24, 32)
    (folder / "b.png").symlink_to(tmp_path / "nowhere.png")
    (folder / "c.png").symlink_to(folder / "c.png")
    (folder / "d.png").symlink_to(folder / "a.png")  # a working link is an input like any other
    out = tmp_path / "out"
    argv = {"simulate": ["simulate", "--no-tilt"], "restore": ["restore", "--weights", "input"]}[command]
    rc, _, err = run_cli(capsys, [*argv, str(folder), "--out", str(out)])
    assert rc == 1
    lines = error_lines(err)
    assert len(lines) == 2 and "Traceback" not in err
    assert "b.png" in lines[0] and "dangling" in lines[0] and "c.png" in lines[1] and "loop" in lines[1]
    suffix = "turb.png" if command == "simulate" else "restored.png"
    assert {f"a_{suffix}", f"d_{suffix}"} <= {p.name for p in out.iterdir()}


# ------------------------------------------------------------------------------------ 10. strict weights
TINY_NAFNET = {"width": 8, "enc_blocks": [1], "dec_blocks": [1]}


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


# ------------------------------------------------------------------------------------- 11. unreadable
@pytest.mark.parametrize(
    "thing", ["input folder", "input file", "clean folder", "config", "dataset.json", "meta.jsonl", "weights"]
)
def test_unreadable_things_are_one_line(thing, tmp_path, run_unprivileged):
    """Mode 000, in a process that file permissions bind (as root too: see the run_unprivileged fixture)."""
    from d2turb.models import create_model, save_pretrained

    folder = tmp_path / "in"
    image = rgb(folder / "a.png", 24, 32)
    root = tiny_pairs(tmp_path / "ds", n=2, size=16, split="test")
    config = tiny_config(tmp_path)
    weights = save_pretrained(create_model("nafnet", **TINY_NAFNET), tmp_path / "w.safetensors")
    evaluate = ["evaluate", "--data", root, "--weights", "input", "--metrics", "psnr", "--out", tmp_path / "o"]
    locked, argv = {
        "input folder": (folder, ["simulate", folder, "--out", tmp_path / "o"]),
        "input file": (image, ["simulate", image, "--out", tmp_path / "o"]),
        "clean folder": (folder, make_dataset_args(folder, tmp_path / "o")),
        "config": (config, ["train", "--config", config, "--out", tmp_path / "o"]),
        "dataset.json": (root / "dataset.json", evaluate),
        "meta.jsonl": (root / "meta.jsonl", evaluate),
        "weights": (weights, ["restore", image, "--weights", weights, "--out", tmp_path / "o"]),
    }[thing]
    mode = locked.stat().st_mode
    locked.chmod(0)
    try:
        proc = run_unprivileged(*argv)
    finally:
        locked.chmod(mode)
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = one_error_line(proc.stderr, str(locked), "Permission denied")
    assert "corrupt" not in line and "FileNotFoundError" not in line


# ------------------------------------------------------------------------ 12. physics that cannot fit
@pytest.mark.parametrize("ifov", ["1", "1e-9", "1e-3"])
def test_a_pixel_scale_that_cannot_fit_in_memory_is_refused_before_allocating(ifov, tmp_path, capsys):
    """--ifov 1 asked the PSF optics for a petabyte, 1e-9 for 1.2 TB, 1e-3 grew to 15 GB on a 32² image. The
    supported range is 1/4 to 16 Nyquist pixels λ/(2D) (docs/cli.md): 6.56e-07 to 4.2e-05 rad at D = 0.1 m,
    λ = 525 nm."""
    image = rgb(tmp_path / "a.png", 32, 32)
    rc, _, err = run_cli(capsys, ["simulate", str(image), "--out", str(tmp_path / "o"), "--ifov", ifov])
    assert rc == 2
    one_error_line(err, "--ifov", "6.56e-07", "4.2e-05")
    argv = make_dataset_args(tmp_path, tmp_path / "ds", "--param", f"ifov_rad={ifov}")
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "ifov_rad", "6.56e-07", "4.2e-05")
    assert not (tmp_path / "o").exists() and not (tmp_path / "ds").exists()


def test_the_ends_of_the_pixel_scale_range_simulate(tmp_path, capsys):
    image = rgb(tmp_path / "a.png", 32, 32)
    for ifov in ("6.6e-7", "4.1e-5"):
        assert main(["simulate", str(image), "--out", str(tmp_path / ifov), "--ifov", ifov, "--no-tilt"]) == 0
    capsys.readouterr()


def test_make_dataset_patch_is_bounded(tmp_path, capsys):
    rgb(tmp_path / "clean" / "a.png", 40, 48)
    argv = make_dataset_args(tmp_path / "clean", tmp_path / "ds")
    argv[argv.index("--patch") + 1] = "100000"
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "--patch", "4096")


# ------------------------------------------------------------------------- 13. Restorer on the padded canvas
def _oracle_warp(canvas: torch.Tensor, flow: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """out(x) = canvas(x + flow(x)) for the top-left h×w pixels, bilinear with the canvas edge clamped, written
    with grid_sample in float64 (align_corners=True: -1 and +1 are the centres of the first and last pixels)."""
    hc, wc = canvas.shape[-2:]
    ys, xs = torch.meshgrid(torch.arange(hc, dtype=torch.float64), torch.arange(wc, dtype=torch.float64), indexing="ij")
    gx = (xs + flow[0, 0].double()) / (wc - 1) * 2 - 1
    gy = (ys + flow[0, 1].double()) / (hc - 1) * 2 - 1
    grid = torch.stack((gx, gy), -1)[None]
    out = torch.nn.functional.grid_sample(canvas.double(), grid, padding_mode="border", align_corners=True)
    return out[..., :h, :w].float()


def _flowing_model():
    """A small D²Turb whose flow points 2.5 px right and 3.5 px down everywhere (the flow head's bias)."""
    from d2turb.models import create_model

    torch.manual_seed(0)
    model = create_model("d2turb_lite", backbone_cfg={"width": 8, "enc_blocks": [1], "dec_blocks": [1]}).eval()
    with torch.no_grad():
        model.rectifier.flow_head.bias.copy_(torch.tensor([2.5, 3.5]))
    return model


def test_restorer_warps_the_padded_canvas_as_the_authors_model_does():
    """The authors pad the input at the bottom/right to a multiple of 32 (reflect), run backbone, rectifier and the
    warp on that canvas, and crop: a flow pointing past the bottom/right edge samples the canvas there."""
    from d2turb.restore import Restorer

    model = _flowing_model()
    image = torch.rand(3, 100, 116, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        canvas = torch.nn.functional.pad(image[None], (0, 128 - 116, 0, 128 - 100), mode="reflect")
        deblurred, guide = model.backbone(canvas)
        flow = model.rectifier(deblurred, guide, size=(100, 116))
    expected = _oracle_warp(deblurred, flow, 100, 116).clamp(0, 1)[0]
    cropped_then_clamped = _oracle_warp(deblurred[..., :100, :116], flow[..., :100, :116], 100, 116).clamp(0, 1)[0]
    assert (cropped_then_clamped - expected).abs().amax() > 0.01  # the two conventions differ at the edges
    restored = Restorer(model, tile=512).restore(image)
    assert torch.allclose(restored, expected, atol=1e-5), (restored - expected).abs().amax()


def test_tiled_warp_samples_the_padded_canvas_too():
    from d2turb.restore.single import warp_in_strips

    g = torch.Generator().manual_seed(2)
    image, flow = torch.rand(1, 3, 100, 116, generator=g), torch.randn(1, 2, 100, 116, generator=g) * 4
    canvas = torch.nn.functional.pad(image, (0, 128 - 116, 0, 128 - 100), mode="reflect")
    padded_flow = torch.nn.functional.pad(flow, (0, 12, 0, 28))
    expected = _oracle_warp(canvas, padded_flow, 100, 116)
    assert torch.allclose(warp_in_strips(image, flow, pad_to=32), expected, atol=1e-5)


def test_file_name_not_utf8_is_one_error_line_and_nothing_written(tmp_path, capsys):
    """A folder holding a file whose name is not valid UTF-8 (Latin-1 bytes): one `error:` line naming it with
    the bytes escaped, exit 2, no output folder (it used to end in a UnicodeEncodeError traceback; issue 37)."""
    folder = tmp_path / "in"
    folder.mkdir()
    pixels = (np.arange(24 * 32 * 3).reshape(24, 32, 3) % 251).astype(np.uint8)
    Image.fromarray(pixels).save(folder / "ok.png")
    Image.fromarray(pixels).save(os.fsdecode(os.fsencode(folder) + b"/caf\xe9.png"))
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, ["simulate", str(folder), "--out", str(out)])
    assert rc == 2
    one_error_line(err, "caf\\xe9.png", "not valid UTF-8")
    assert not out.exists()


@pytest.mark.parametrize("inherited", ["default", "ignored"])
def test_ctrl_c_during_simulate_stops_cleans_up_and_exits_130(tmp_path, inherited):
    """SIGINT while `simulate` works through 64 images: exit 130 with one `interrupted` line, no temp file left,
    every output it finished complete (turb, tilt and meta of each image), the rest not started. Also when the
    process was started with SIGINT ignored (a script's `cmd &`), which it used to inherit and run to the end."""
    folder, out = tmp_path / "in", tmp_path / "out"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(64):
        Image.fromarray((rng.random((48, 64, 3)) * 255).astype(np.uint8)).save(folder / f"img{i:02d}.png")
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if inherited == "ignored" else None
    cmd = [sys.executable, "-m", "d2turb", "simulate", str(folder), "--out", str(out), "--seed", "1"]
    proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=ignore)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if out.is_dir() and len(list(out.glob("*_meta.json"))) >= 2:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    err = err.decode()
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["interrupted"] and "Traceback" not in err
    names = sorted(p.name for p in out.iterdir())
    assert not [n for n in names if n.startswith(".") or ".tmp" in n], names
    done = sorted(n.removesuffix("_meta.json") for n in names if n.endswith("_meta.json"))
    assert 2 <= len(done) < 64
    assert names == sorted(f"{stem}_{kind}" for stem in done for kind in ("meta.json", "tilt.png", "turb.png"))
    for stem in done:
        assert Image.open(out / f"{stem}_turb.png").size == (64, 48)
