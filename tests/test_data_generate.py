"""make-dataset / check-dataset: plans, files, resume after SIGKILL, 2-process run, problem detection."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hostile_input import CHILD_ENV, make_dataset_args, one_error_line, png_bomb, rgb, run_cli, run_killed_at_rename
from PIL import Image
from scipy import stats

from d2turb.cli import main
from d2turb.data import check_dataset, plan_sample
from d2turb.data.layout import FILES, read_depth_png
from d2turb.data.plan import crop_box
from d2turb.data.sources import resize_up
from d2turb.io import read_image
from d2turb.sim import BINS, bin_spans, dr0_bin, dr0_from_uniform

PATCH, PAIRS, BATCH = 64, 6, 2
ENV = {**os.environ, "OMP_NUM_THREADS": "2", "PYTHONUNBUFFERED": "1"}


def make_args(clean, out, pairs=PAIRS, split="test", extra=()):
    return [
        "make-dataset",
        "--clean",
        str(clean),
        "--out",
        str(out),
        "--pairs",
        str(pairs),
        "--patch",
        str(PATCH),
        "--split",
        split,
        "--batch",
        str(BATCH),
        "--seed",
        "7",
        "--depth",
        "prior",
        "--device",
        "cpu",
        "--no-progress",
        *extra,
    ]


@pytest.fixture(scope="module")
def clean_dir(tmp_path_factory):
    from skimage import data

    folder = tmp_path_factory.mktemp("clean")
    Image.fromarray(data.astronaut()[::4, ::4]).save(folder / "a_astronaut.png")  # 128x128
    Image.fromarray(data.coffee()[::4, ::5]).save(folder / "b_coffee.png")  # 100x120
    Image.fromarray(data.camera()[::12, ::10]).save(folder / "c_camera_small.png")  # 43x52 grey, < patch
    return folder


@pytest.fixture(scope="module")
def reference(clean_dir, tmp_path_factory):
    """A clean, uninterrupted run (in-process) that the other runs are compared with."""
    torch.set_num_threads(2)
    out = tmp_path_factory.mktemp("ref") / "ds"
    assert main(make_args(clean_dir, out)) == 0
    return out


def tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def assert_same_tree(a: Path, b: Path):
    ta, tb = tree_bytes(a), tree_bytes(b)
    assert sorted(ta) == sorted(tb)
    different = [k for k in ta if ta[k] != tb[k]]
    assert not different, f"files differ: {different[:5]}"


# ------------------------------------------------------------------------------------------- planning
def test_test_split_is_balanced_and_inside_bins():
    bins = ("weak", "medium", "strong")
    plans = [plan_sample(i, 3, "test", bins, n_sources=5) for i in range(60)]
    assert [p.bin for p in plans] == [bins[i % 3] for i in range(60)]
    for p in plans:
        lo, hi = BINS[p.bin]
        assert lo <= p.dr0 <= hi
        assert p.source == (p.index // 3) % 5
        assert 0 <= p.crop_u < 1 and 0 <= p.crop_v < 1


def test_train_dr0_is_uniform_over_union_of_bins():
    rng = np.random.default_rng(0)
    values = dr0_from_uniform(rng.random(3000), bin_spans(("weak", "strong")))
    assert ((values >= 1.0) & (values <= 2.25) | (values >= 3.75) & (values <= 5.0)).all()
    folded = np.where(values <= 2.25, values - 1.0, values - 3.75 + 1.25)  # union mapped onto [0, 2.5)
    assert stats.kstest(folded, stats.uniform(0, 2.5).cdf).pvalue > 1e-3
    plans = [plan_sample(i, 0, "train", ("weak", "strong"), n_sources=4) for i in range(200)]
    assert {p.bin for p in plans} == {"weak", "strong"}
    assert all(p.bin == dr0_bin(p.dr0) for p in plans)


def test_plan_depends_only_on_seed_and_index():
    a = [plan_sample(i, 11, "train", ("medium",), 7) for i in (5, 0, 3)]
    b = [plan_sample(i, 11, "train", ("medium",), 7) for i in (3, 5, 0)]
    assert a[0] == b[1] and a[1] == b[2] and a[2] == b[0]
    assert plan_sample(5, 12, "train", ("medium",), 7) != a[0]


def test_small_images_are_resized_up_and_crops_stay_inside():
    img = torch.rand(3, 40, 90)
    up = resize_up(img, 64)
    assert up.shape == (3, 64, 144)
    assert resize_up(torch.rand(3, 70, 80), 64).shape == (3, 70, 80)
    for i in range(50):
        x0, y0, x1, y1 = crop_box(plan_sample(i, 0, "train", ("weak",), 1), 64, 144, 64)
        assert 0 <= x0 and x1 <= 144 and y0 == 0 and y1 == 64 and x1 - x0 == 64


# --------------------------------------------------------------------------------------- generation
@pytest.mark.slow
def test_generated_dataset_is_valid_and_consistent(reference, clean_dir, capsys):
    assert main(["check-dataset", str(reference)]) == 0
    out = capsys.readouterr().out
    assert "6 samples (weak 2, medium 2, strong 2)" in out
    config = json.loads((reference / "dataset.json").read_text())
    assert config["pairs"] == PAIRS and config["patch"] == PATCH and config["split"] == "test" and config["seed"] == 7
    meta = [json.loads(line) for line in (reference / "meta.jsonl").read_text().splitlines()]
    assert [m["index"] for m in meta] == list(range(PAIRS))
    from d2turb.depth.prior import estimate_depth_prior

    for m in meta:
        assert {"id", "source", "crop", "dr0", "bin", "seed", "params"} <= set(m)
        x0, y0, x1, y1 = m["crop"]
        source = read_image(m["source"])
        full_depth = estimate_depth_prior(source).reshape(1, *source.shape[-2:])
        source, full_depth = resize_up(source, PATCH), resize_up(full_depth, PATCH)
        assert list(source.shape[-2:][::-1]) == m["source_size"]
        gt = read_image(reference / "gt" / f"{m['id']}.png")
        # gt is exactly the crop of the (resized) source image, depth the crop of the full-image depth
        assert torch.equal(torch.round(gt * 255), torch.round(source[:, y0:y1, x0:x1] * 255))
        depth = read_depth_png(reference / "depth" / f"{m['id']}.png")
        assert torch.allclose(depth, full_depth[:, y0:y1, x0:x1], atol=1 / 65535 + 1e-6)
    # every source (small grey one included) is used, in the balanced test order
    assert [Path(m["source"]).name for m in meta[::3]] == ["a_astronaut.png", "b_coffee.png"]


def test_flow_undoes_the_tilt(reference):
    from d2turb.data import PairDataset
    from d2turb.ops import warp

    ds = PairDataset(reference, split="test")
    err_flow = err_none = 0.0
    for k in range(len(ds)):
        s = ds[k]
        inner = (slice(None), slice(8, -8), slice(8, -8))
        err_flow += (warp(s["tilt"][None], s["bwd_flow_px"][None])[0] - s["gt"])[inner].abs().mean().item()
        err_none += (s["tilt"] - s["gt"])[inner].abs().mean().item()
    assert err_flow < 0.8 * err_none


def test_interrupted_state_is_repaired_byte_identically(reference, clean_dir, tmp_path):
    """Meta split into shards with a torn last line, a sample without meta, one with a missing file and a
    leftover temp file: the rerun, on another number of threads, completes to exactly the reference."""
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    lines = (out / "meta.jsonl").read_text().splitlines(keepends=True)
    (out / "meta.jsonl").unlink()
    (out / ".meta").mkdir()
    (out / ".meta" / "rank-0.jsonl").write_text("".join(lines[:2]) + lines[2][:25])  # torn line 3
    (out / ".meta" / "rank-1.jsonl").write_text(lines[4])
    (out / "bwd_flow_px" / "0000004.npy").unlink()  # meta line present but file missing → not done
    (out / "turb" / ".0000003.png.abcd.tmp.png").write_bytes(b"partial")
    assert check_dataset(out).problems
    torch.set_num_threads(3)  # the reference was made on 2: a resume on another machine or load gives the same bytes
    assert main(make_args(clean_dir, out)) == 0
    assert_same_tree(reference, out)


@pytest.mark.slow
def test_sigkill_then_rerun_matches_clean_run(clean_dir, tmp_path, capsys):
    """A generation process killed with SIGKILL part-way through writing a sample leaves a dataset check-dataset
    calls broken; the same command run again (here in this process: what it resumes from is on disk) finishes it
    byte-identically."""
    pairs = 12
    ref = tmp_path / "ref"
    assert main(make_args(clean_dir, ref, pairs=pairs)) == 0
    out = tmp_path / "killed"
    # killed at its 19th file rename (dataset.json, then 5 files a sample): inside chunk 1, a file left under its
    # temporary name
    proc = run_killed_at_rename(19, make_args(clean_dir, out, pairs=pairs), env=ENV)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    done_before = (out / ".meta" / "rank-0.jsonl").read_bytes().count(b"\n")
    assert 2 <= done_before < 4
    assert any(".tmp" in p.name for p in out.rglob("*"))
    assert main(["check-dataset", str(out)]) == 1  # unfinished dataset is reported broken
    capsys.readouterr()
    assert main(make_args(clean_dir, out, pairs=pairs)) == 0
    stats_line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert stats_line["generated"] == pairs - stats_line["already_done"] and stats_line["already_done"] >= done_before
    assert check_dataset(out).ok
    assert_same_tree(ref, out)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_ranks_match_single_process(reference, clean_dir, tmp_path):
    out = tmp_path / "ds"
    port = str(_free_port())
    cmd = [sys.executable, "-m", "d2turb", *make_args(clean_dir, out)]
    procs = [
        subprocess.Popen(
            cmd,
            env={
                **ENV,
                "RANK": str(r),
                "LOCAL_RANK": str(r),
                "WORLD_SIZE": "2",
                "MASTER_ADDR": "127.0.0.1",
                "MASTER_PORT": port,
            },
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for r in range(2)
    ]
    results = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], results
    rank0 = json.loads(results[0][0].strip().splitlines()[-1])
    assert rank0["world"] == 2 and 0 < rank0["generated"] < PAIRS  # the work was really shared
    assert_same_tree(reference, out)


# ------------------------------------------------------------------------------------------ checking
def test_check_dataset_reports_each_problem(reference, tmp_path, capsys):
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    (out / "depth" / "0000000.png").unlink()
    (out / "turb" / "0000001.png").write_bytes((out / "turb" / "0000001.png").read_bytes()[:60])
    np.save(out / "bwd_flow_px" / "0000002.npy", np.full((2, PATCH, PATCH), np.nan, np.float16))
    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(out / "tilt" / "0000003.png")
    shutil.copy(out / "gt" / "0000004.png", out / "gt" / "9999999.png")
    lines = (out / "meta.jsonl").read_text().splitlines(keepends=True)
    bad_bin = json.loads(lines[5])
    bad_bin["dr0"] = 1.5 if bad_bin["bin"] != "weak" else 4.5
    (out / "meta.jsonl").write_text("".join(lines[:5]) + json.dumps(bad_bin) + "\n" + lines[4])
    report = check_dataset(out)
    text = "\n".join(report.problems)
    for expected in [
        "0000000: missing depth/0000000.png",
        "0000001: turb does not decode",
        "0000002: bwd_flow_px contains NaN",
        "0000003: tilt is RGB 32x32",
        "orphan file gt/9999999.png",
        "0000005: D/r0 = ",
        "0000004: duplicate id",
    ]:
        assert expected in text
    assert len(report.problems) == 7, text
    assert main(["check-dataset", str(out)]) == 1
    assert "7 problem(s)" in capsys.readouterr().err


def test_bad_input_gives_clear_errors(clean_dir, reference, tmp_path, capsys):
    assert main(make_args(clean_dir, tmp_path / "a", extra=["--bins", "weak,extreme"])) == 2
    assert "unknown bin 'extreme'" in capsys.readouterr().err
    assert main(make_args(clean_dir, tmp_path / "a", extra=["--param", "no_such_field=1"])) == 2
    assert "bad simulator parameter" in capsys.readouterr().err
    assert main(make_args(clean_dir, tmp_path / "a", extra=["--param", "offset_s"])) == 2
    assert "--param expects KEY=VALUE" in capsys.readouterr().err
    assert main(make_args(tmp_path / "missing", tmp_path / "b")) == 2
    assert "no such file or directory" in capsys.readouterr().err
    # rerunning into an existing dataset with other settings is refused
    assert main(make_args(clean_dir, reference, pairs=PAIRS + 1)) == 2
    assert "different settings (pairs)" in capsys.readouterr().err
    assert main(["check-dataset", str(tmp_path)]) == 2
    assert "not a d2turb dataset" in capsys.readouterr().err


def test_corrupt_source_is_skipped_with_warning(clean_dir, tmp_path, caplog):
    src = tmp_path / "src"
    shutil.copytree(clean_dir, src)
    (src / "0_broken.png").write_bytes(b"\x89PNG not really")
    out = tmp_path / "ds"
    assert main(make_args(src, out, pairs=3, extra=["--depth", "none"])) == 0
    assert any("0_broken.png" in r.getMessage() and r.levelname == "WARNING" for r in caplog.records)
    assert check_dataset(out).ok
    meta = [json.loads(line) for line in (out / "meta.jsonl").read_text().splitlines()]
    assert all("0_broken" not in m["source"] for m in meta)
    assert torch.equal(read_depth_png(out / "depth" / "0000000.png"), torch.ones(1, PATCH, PATCH))
    assert set(FILES) <= {p.name for p in out.iterdir()}


def test_real_clean_images(shared_data, tmp_path):
    files = sorted((shared_data / "clean" / "bsd100").iterdir())[:2]
    if len(files) < 2:
        pytest.skip("bsd100 images absent")
    out = tmp_path / "ds"
    assert (
        main(
            [
                "make-dataset",
                "--clean",
                *map(str, files),
                "--out",
                str(out),
                "--pairs",
                "2",
                "--patch",
                "64",
                "--split",
                "test",
                "--bins",
                "medium,strong",
                "--depth",
                "none",
                "--device",
                "cpu",
                "--no-progress",
            ]
        )
        == 0
    )
    report = check_dataset(out)
    assert report.ok and report.counts == {"medium": 1, "strong": 1}


def test_meta_has_one_dr0_the_sample_s(tmp_path, capsys):
    """A sample's metadata holds its true D/r0 once (``dr0``, inside its bin); the simulator parameters beside it
    carry no second, default D/r0 or the r0 derived from it (they were 3.0 beside a sample's 3.55)."""
    from PIL import Image

    from d2turb.cli import main

    clean = tmp_path / "clean"
    clean.mkdir()
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (40, 48, 3), dtype=np.uint8)).save(clean / "a.png")
    argv = ["make-dataset", "--clean", str(clean), "--out", str(tmp_path / "ds"), "--pairs", "3", "--patch", "16"]
    assert main([*argv, "--depth", "none", "--device", "cpu", "--no-progress"]) == 0
    capsys.readouterr()
    for line in (tmp_path / "ds" / "meta.jsonl").read_text().splitlines():
        rec = json.loads(line)
        lo, hi = BINS[rec["bin"]]
        assert lo <= rec["dr0"] <= hi
        assert "dr0" not in rec["params"] and "r0_m" not in rec["params"]
    record = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert "dr0" not in record["params"]


def test_make_dataset_skips_a_bomb_like_other_unreadable_sources(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    png_bomb(clean / "b_bomb.png")
    rc, _, err = run_cli(capsys, make_dataset_args(clean, tmp_path / "ds"))
    assert rc == 0, err
    assert "b_bomb.png" in err and "100000x100000" in err and "Traceback" not in err
    meta = [json.loads(line) for line in (tmp_path / "ds" / "meta.jsonl").read_text().splitlines()]
    assert len(meta) == 2 and all(m["source"].endswith("a.png") for m in meta)


def test_failed_make_dataset_does_not_lock_the_folder(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    (tmp_path / "no_maps").mkdir()
    out = tmp_path / "ds"
    rc, _, err = run_cli(capsys, make_dataset_args(clean, out, depth=str(tmp_path / "no_maps")))
    assert rc == 2
    one_error_line(err, "no depth file")
    assert not (out / "dataset.json").exists()
    assert main(make_dataset_args(clean, out)) == 0  # the corrected run, same --out
    # a config left by a run killed before its first sample does not lock the folder either
    killed = tmp_path / "killed"
    assert main(make_dataset_args(clean, killed, "--seed", "5")) == 0
    (killed / "meta.jsonl").unlink()  # as if killed before any sample's meta line was written
    (killed / "turb" / "0000000.png").unlink()
    assert main(make_dataset_args(clean, killed)) == 0
    assert json.loads((killed / "dataset.json").read_text())["seed"] == 0
    assert main(["check-dataset", str(killed)]) == 0
    capsys.readouterr()


def test_patch_larger_than_every_source_is_refused(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 96, 96)
    rgb(clean / "b.png", 64, 90)
    argv = make_dataset_args(clean, tmp_path / "ds")
    argv[argv.index("--patch") + 1] = "4096"
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "--patch 4096", "96 px")
    assert not (tmp_path / "ds").exists()


def test_small_sources_are_reported(tmp_path, capsys):
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    rgb(clean / "b.png", 12, 14)
    rc, _, err = run_cli(capsys, make_dataset_args(clean, tmp_path / "ds", "--split", "train", "--pairs", "6"))
    assert rc == 0
    assert err.count("b.png is 14x12, smaller than the 16-px patch: resized up") == 1


def test_two_make_dataset_runs_into_one_folder(tmp_path, capsys):
    """The second run is refused in one line naming the first one's process; a lock left by a killed run
    (its process gone) is taken over."""
    clean = tmp_path / "clean"
    rgb(clean / "a.png", 40, 48)
    out = tmp_path / "ds"
    first = subprocess.Popen(
        [sys.executable, "-m", "d2turb", *make_dataset_args(clean, out, "--pairs", "4000")],
        env=CHILD_ENV,
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


def test_make_dataset_patch_is_bounded(tmp_path, capsys):
    rgb(tmp_path / "clean" / "a.png", 40, 48)
    argv = make_dataset_args(tmp_path / "clean", tmp_path / "ds")
    argv[argv.index("--patch") + 1] = "100000"
    rc, _, err = run_cli(capsys, argv)
    assert rc == 2
    one_error_line(err, "--patch", "4096")
