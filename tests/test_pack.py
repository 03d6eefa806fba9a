"""d2turb make-pack / d2turb.data.pack: the fixed split, pack round trip, determinism, size budget, refusal of test
folders and of tampered packs, restart after an interruption, and in-memory crops."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hostile_input import one_error_line, rgb, run_cli
from PIL import Image

from d2turb.data.pack import make_pack
from d2turb.data.pack_read import MANIFEST, PackCrops, decode_pack, read_pack
from d2turb.data.split import split_of
from d2turb.errors import D2TurbError


@pytest.fixture(autouse=True)
def _one_thread(_torch_threads):
    torch.set_num_threads(1)


def smooth_image(w: int, h: int, seed: int) -> np.ndarray:
    """A smooth RGB image (JPEG at quality 90 keeps it within a few grey levels)."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 255, size=(4, 4, 3)).astype(np.uint8)
    return np.asarray(Image.fromarray(coarse).resize((w, h), Image.Resampling.BICUBIC))


def write(path: Path, pixels: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(path)


@pytest.fixture(scope="module")
def clean_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("clean")
    write(root / "urban100" / "a.png", smooth_image(80, 60, 0))
    write(root / "urban100" / "b.jpg", smooth_image(64, 64, 1))
    write(root / "urban100" / "tiny.png", smooth_image(40, 24, 2))  # short side below the 32 px patch
    write(root / "set14" / "c.png", smooth_image(50, 50, 3))
    write(root / "mcmaster" / "d.png", smooth_image(48, 36, 4))
    write(root / "bsd100" / "e.png", smooth_image(40, 40, 5))  # test folder: must never enter a pack
    (root / "MANIFEST.csv").write_text(
        "file,width,height,source_repo,commit,source_path\nurban100/a.png,80,60,github:o/r,abc123,imgs/a.png\n"
    )
    return root


@pytest.fixture(scope="module")
def pack(clean_root, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("packs") / "pack"
    make_pack([clean_root], out, patch=32, max_mib=1.0)
    return out


def files_of(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_split_definition(clean_root):
    assert [split_of(f) for f in ("data/bsd100", "sunhays_outdoor", "set14", "mcmaster")] == [
        "test",
        "test",
        "val",
        "val",
    ]
    assert {split_of(f) for f in ("urban100", "bsds500", "camvid", "strecha_mvs", "sfm_landmarks", "t91")} == {"train"}
    assert split_of("my_own_photos") == "train"  # train = every other folder
    folders = sorted(p for p in clean_root.iterdir() if p.is_dir())
    assert [p.name for p in folders if split_of(p) == "val"] == ["mcmaster", "set14"]
    assert [p.name for p in folders if split_of(p) == "test"] == ["bsd100"]


def test_pack_round_trip_and_manifest(clean_root, pack):
    manifest = json.loads((pack / MANIFEST).read_text())
    assert manifest["counts"] == {"train": 3, "val": 2} and manifest["excluded_test_folders"] == ["bsd100"]
    assert not any("bsd100" in name for name in files_of(pack))
    total = 0
    for entry in manifest["images"]:
        data = (pack / entry["file"]).read_bytes()
        source = clean_root / entry["source"]
        assert entry["sha256"] == hashlib.sha256(data).hexdigest() and entry["bytes"] == len(data)
        assert entry["source_sha256"] == hashlib.sha256(source.read_bytes()).hexdigest()
        assert entry["split"] == ("val" if entry["folder"] in ("set14", "mcmaster") else "train")
        original = np.asarray(Image.open(source).convert("RGB"), dtype=np.float64)
        stored = np.asarray(Image.open(pack / entry["file"]).convert("RGB"), dtype=np.float64)
        assert stored.shape == original.shape  # small images are never resized
        assert 10 * np.log10(255.0**2 / ((stored - original) ** 2).mean()) > 35  # JPEG q90 of a smooth image
        total += len(data)
    origin = next(e for e in manifest["images"] if e["source"] == "urban100/a.png")["origin"]
    assert origin == {"source_repo": "github:o/r", "commit": "abc123", "source_path": "imgs/a.png"}
    on_disk = sum(len(b) for b in files_of(pack).values())
    assert on_disk == total + (pack / MANIFEST).stat().st_size <= 1 << 20
    images, depths, names = decode_pack(pack, "val", patch=32, depth="none")
    assert depths is None and names == ["mcmaster/d", "set14/c"]
    assert [tuple(i.shape) for i in images] == [(3, 36, 48), (3, 50, 50)] and images[0].dtype == torch.uint8
    assert torch.equal(images[1].permute(1, 2, 0), torch.from_numpy(np.array(Image.open(pack / "val/set14/c.jpg"))))


def test_pack_is_deterministic_and_up_to_date(clean_root, pack, tmp_path):
    folders = [clean_root / "urban100", clean_root / "set14", clean_root / "mcmaster"]
    make_pack(folders, tmp_path / "direct", 1.0, 32)  # the same folders named one by one: the same images
    direct, reference = files_of(tmp_path / "direct"), files_of(pack)
    assert direct.pop(MANIFEST) != reference.pop(MANIFEST) and direct == reference  # (no test folder excluded)
    summary = make_pack([clean_root], tmp_path / "p", 1.0, 32)
    assert files_of(tmp_path / "p") == files_of(pack) and summary["up_to_date"] is False
    again = make_pack([clean_root], tmp_path / "p", 1.0, 32)
    assert again["up_to_date"] is True and files_of(tmp_path / "p") == files_of(pack)
    (tmp_path / "p" / "train" / "urban100" / "a.jpg").write_bytes(b"damaged")
    assert make_pack([clean_root], tmp_path / "p", 1.0, 32)["up_to_date"] is False  # a damaged pack is rebuilt
    assert files_of(tmp_path / "p") == files_of(pack) and not (tmp_path / ".p.partial").exists()


def test_pack_fits_its_budget_by_downscaling(tmp_path):
    rng = np.random.default_rng(0)
    for i in range(2):  # noise hardly compresses: ~0.1 MiB each at full size
        write(tmp_path / "clean" / "camvid" / f"{i}.png", rng.integers(0, 256, size=(300, 400, 3), dtype=np.uint8))
    summary = make_pack([tmp_path / "clean"], tmp_path / "p", max_mib=0.15, patch=48)
    assert summary["long_side_cap"] is not None and summary["bytes"] <= 0.15 * (1 << 20)
    assert sum(len(b) for b in files_of(tmp_path / "p").values()) == summary["bytes"]
    for entry in json.loads((tmp_path / "p" / MANIFEST).read_text())["images"]:
        w, h = Image.open(tmp_path / "p" / entry["file"]).size
        assert max(w, h) <= summary["long_side_cap"] and min(w, h) >= 48 and abs(w / h - 400 / 300) < 0.02
    with pytest.raises(D2TurbError, match="does not fit"):
        make_pack([tmp_path / "clean"], tmp_path / "q", max_mib=0.01, patch=48)
    assert not (tmp_path / "q").exists()


def test_pack_refuses_test_folders_and_tampering(clean_root, pack, tmp_path, capsys):
    from d2turb.cli import main

    with pytest.raises(D2TurbError, match="test folder"):
        make_pack([clean_root / "bsd100"], tmp_path / "p")
    assert main(["make-pack", "--clean", str(clean_root / "bsd100"), "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "test folder" in err[0]
    assert not (tmp_path / "p").exists()
    bad = tmp_path / "bad"
    bad.mkdir()
    for name, data in files_of(pack).items():
        (bad / name).parent.mkdir(parents=True, exist_ok=True)
        (bad / name).write_bytes(data)
    manifest = json.loads((bad / MANIFEST).read_text())
    manifest["images"][0]["split"] = "test"
    (bad / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(D2TurbError, match="test image"):
        read_pack(bad)
    manifest["images"][0]["split"] = "train"
    (bad / MANIFEST).write_text(json.dumps(manifest))
    target = bad / manifest["images"][0]["file"]
    target.write_bytes(target.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(D2TurbError, match="checksum"):
        read_pack(bad)
    with pytest.raises(D2TurbError, match="not a d2turb pack"):
        read_pack(tmp_path)


def test_pack_restarts_after_an_interruption(clean_root, pack, tmp_path, monkeypatch):
    import d2turb.data.pack as pack_module

    real, calls, armed = pack_module.encode_jpeg, [], [True]

    def dying(*args, **kwargs):
        calls.append(1)
        if armed[0] and len(calls) == 3:
            raise KeyboardInterrupt  # the process dies while encoding the third image
        return real(*args, **kwargs)

    monkeypatch.setattr(pack_module, "encode_jpeg", dying)
    with pytest.raises(KeyboardInterrupt):
        make_pack([clean_root], tmp_path / "p", 1.0, 32)
    assert not (tmp_path / "p").exists() and (tmp_path / ".p.partial").is_dir()  # nothing half-written
    calls.clear()
    armed[0] = False
    make_pack([clean_root], tmp_path / "p", 1.0, 32)
    assert len(calls) == 5 - 2  # the two images encoded before the interruption are reused
    assert files_of(tmp_path / "p") == files_of(pack) and not (tmp_path / ".p.partial").exists()


def test_pack_crops_in_memory(pack):
    crops = PackCrops(pack, patch=32, length=7, depth="none", hflip=True, vflip=True, seed=3)
    assert len(crops) == 7 and crops.names == ["urban100/a", "urban100/b", "urban100/tiny"]
    assert min(crops.images[2].shape[-2:]) == 32  # 40×24 resized up to a 32 px short side once, at decode
    seen = []
    for i in range(7):
        item = crops[i]
        name, xy = item["id"].split("@")
        x0, y0 = map(int, xy.split(","))
        image = crops.images[crops.names.index(name)].float() / 255
        window = image[:, y0 : y0 + 32, x0 : x0 + 32]
        variants = [window, window.flip(-1), window.flip(-2), window.flip(-1).flip(-2)]
        assert item["gt"].shape == (3, 32, 32) and any(torch.equal(item["gt"], v) for v in variants)
        assert torch.equal(item["depth"], torch.ones(1, 32, 32))
        seen.append(item["gt"])
    state = crops.generator.get_state()
    first = crops[0]["gt"]
    crops.generator.set_state(state)
    assert torch.equal(crops[0]["gt"], first)  # the crop stream is the generator's alone
    again = PackCrops(pack, patch=32, length=7, depth="none", hflip=True, vflip=True, seed=3)
    assert all(torch.equal(again[i]["gt"], seen[i]) for i in range(7))
    with_depth = PackCrops(pack, patch=32, split="val", depth="prior")
    item = with_depth[0]
    assert item["depth"].shape == (1, 32, 32) and 0 <= float(item["depth"].min()) <= float(item["depth"].max()) <= 1
    centre = with_depth.center_crops(32)
    assert [c["id"] for c in centre] == ["mcmaster/d", "set14/c"] and centre[1]["gt"].shape == (3, 32, 32)
    assert torch.equal(centre[1]["gt"], with_depth.images[1][:, 9:41, 9:41].float() / 255)  # (50 − 32) / 2 = 9


def test_a_pack_entry_that_leaves_the_pack_is_refused(tmp_path):
    from d2turb.data.pack import make_pack
    from d2turb.data.pack_read import read_pack
    from d2turb.errors import D2TurbError

    for i in range(2):
        rgb(tmp_path / "clean" / "folder" / f"{i}.png", 64, 64, seed=i)
    make_pack([tmp_path / "clean" / "folder"], tmp_path / "pack", patch=32, progress=False)
    manifest = json.loads((tmp_path / "pack" / "pack.json").read_text())
    manifest["images"][0]["file"] = "../clean/folder/0.png"
    (tmp_path / "pack" / "pack.json").write_text(json.dumps(manifest))
    with pytest.raises(D2TurbError, match=r"pack\.json.*\.\./clean/folder/0\.png"):
        read_pack(tmp_path / "pack", verify=False)


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
