"""`d2turb evaluate --real-clips DIR` (d2turb.eval.real_clips): per clip a contact sheet, NIQE/PIQE and what a person
sees (d2turb.eval.artifacts) of input | mean fusion | --deblur none | default, the residual frame-to-frame motion and
the blind estimate, from one restoring pass per restoration (the default's, --deblur none's)."""

import json

import cv2
import numpy as np
import pytest
import torch
from skimage import data

from d2turb.cli import main
from d2turb.io import write_image


def _scene(h=96, w=192):
    img = cv2.resize(data.astronaut(), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    return cv2.GaussianBlur(img, (0, 0), 1.2)


def _write_clip(folder, n=12, noise=0.01, seed=0, jitter=False):
    rng = np.random.default_rng(seed)
    img = _scene()
    for i in range(n):
        frame = img
        if jitter:  # a global sub-pixel wobble per frame (what the restoration steadies)
            m = np.float32([[1, 0, rng.uniform(-1.5, 1.5)], [0, 1, rng.uniform(-1.5, 1.5)]])
            frame = cv2.warpAffine(img, m, img.shape[1::-1], borderMode=cv2.BORDER_REFLECT)
        frame = np.clip(frame + noise * rng.standard_normal(img.shape), 0, 1).astype(np.float32)
        write_image(folder / f"f{i:02d}.png", torch.from_numpy(frame).permute(2, 0, 1))


def test_report_writes_sheets_and_results_from_one_registration_pass_per_restoration(tmp_path, monkeypatch, capsys):
    """Each clip is registered once per restoration (passes × frames flows; the motion adds one flow per
    consecutive pair of the input and of each output): the mean fusion and the default come from the same
    ClipFrames, --deblur none from its own restorer."""
    from d2turb.clip import registration

    calls = {"flow": 0}
    real_call = registration.DenseFlow.__call__

    def counting(self, *args, **kwargs):
        calls["flow"] += 1
        return real_call(self, *args, **kwargs)

    monkeypatch.setattr(registration.DenseFlow, "__call__", counting)
    from d2turb.eval import real_clips

    built = []
    real_builder = real_clips.clip_restorer  # restore --temporal's own builder of the restorer and its deblur

    def builder(*args, **kwargs):
        built.append(kwargs)
        return real_builder(*args, **kwargs)

    monkeypatch.setattr(real_clips, "clip_restorer", builder)
    root = tmp_path / "real"
    _write_clip(root / "clipA", jitter=True)
    for i in range(2):  # two frames: not a clip, listed
        write_image(root / "pair" / f"p{i}.png", torch.rand(3, 32, 32))
    out = tmp_path / "out"
    assert main(["evaluate", "--real-clips", str(root), "--temporal", "6", "--out", str(out)]) == 0
    assert calls["flow"] == 2 * (2 * 12 + 11) + 3 * 11  # per restoration two rounds and 11 placements (clip.camera)
    assert len(built) == 2 and "deblur" not in built[0]  # restore's default deblur (auto: the blind one)
    assert built[1] == {"deblur": "none"}  # --deblur none: its own fusion (the sharpest)
    res = json.loads((out / "results.json").read_text())
    entry = res["clips"]["clipA"]
    assert entry["frames"] == 12 and entry["temporal"] == 6 and entry["size"] == [192, 96]
    assert set(entry["niqe"]) == set(entry["piqe"]) == set(entry["measures"]) == {"input", "mean", "none", "default"}
    assert set(entry["checks"]) == set(entry["ghost"]) == {"mean", "none", "default"}
    assert all(np.isfinite(v) for m in entry["measures"].values() for v in m.values())
    # the shake's ghost check: the frames farthest from the middle frame's pose and the nearest
    assert len(entry["shake"]["shift_px"]) == 12 and entry["shake"]["shift_px"][6] == 0
    assert len(entry["shake"]["shaken_frames"]) == len(entry["shake"]["calm_frames"]) == 3
    assert set(entry["crops"]) == {"textured", "tails", "blocks", "noise", "sharpness", "ghost"}
    assert all(np.isfinite(v) for v in entry["piqe"].values())
    assert entry["deblur"]["method"] == "blind" and "estimate" in entry["deblur"]
    # the restoration steadies the wobbling scene
    assert entry["motion_px"]["default"] < 0.5 * entry["motion_px"]["input"]
    sheet = cv2.imread(str(out / entry["sheet"]))
    assert sheet is not None and sheet.shape[1] > 4 * 320 and sheet.shape[0] > 6 * 2 * entry["crops"]["ghost"]["side"]
    assert res["not_clips"] == [{"path": "pair", "reason": "2 image(s): a clip needs at least 4 frames"}]
    md = (out / "results.md").read_text()
    assert "| clipA | 12 |" in md and "Not clips" in md and "| clipA (" in md


def test_identical_frames_have_no_residual_motion(tmp_path):
    from d2turb.eval.real_clips import evaluate_real_clips

    _write_clip(tmp_path / "real" / "still", noise=0.0)
    res = evaluate_real_clips(tmp_path / "real", tmp_path / "out", temporal=4, max_frames=12, progress=False)
    motion = res["clips"]["still"]["motion_px"]
    assert motion["input"] < 1e-3 and motion["default"] < 1e-3


def test_a_bad_folder_is_one_error_line(tmp_path, capsys):
    assert main(["evaluate", "--real-clips", str(tmp_path / "missing"), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "not a directory" in err[0]
    write_image(tmp_path / "few" / "a" / "x.png", torch.rand(3, 32, 32))
    assert main(["evaluate", "--real-clips", str(tmp_path / "few"), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "no clips" in err[0]
    for args in (["--max-frames", "4", "--temporal", "6"], ["--temporal", "1"]):
        assert main(["evaluate", "--real-clips", str(tmp_path / "few"), "--out", str(tmp_path / "o3"), *args]) == 2
        assert capsys.readouterr().err.startswith("error:")


def test_a_clip_that_fails_is_reported_and_the_others_done(tmp_path, capsys):
    root = tmp_path / "real"
    _write_clip(root / "good", n=10)
    _write_clip(root / "short", n=5)  # no longer than the window
    out = tmp_path / "out"
    assert main(["evaluate", "--real-clips", str(root), "--temporal", "6", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "must be shorter than the clip" in err
    res = json.loads((out / "results.json").read_text())
    assert list(res["clips"]) == ["good"] and res["skipped"][0]["clip"] == "short"
    assert (out / "sheets" / "good.png").exists()


def test_textured_window_finds_the_detail():
    from d2turb.eval.real_clip_measures import textured_window

    img = torch.full((3, 120, 200), 0.5)
    img[:, 40:72, 120:152] = torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(0))
    y, x = textured_window(img, 32)
    assert abs(y - 40) <= 8 and abs(x - 120) <= 8


@pytest.mark.parametrize("option", ["--max-frames"])
def test_real_clips_options_need_real_clips(tmp_path, capsys, option):
    assert main(["evaluate", "--real", str(tmp_path), option, "8", "--out", str(tmp_path / "o")]) == 2
    assert "--real-clips" in capsys.readouterr().err
