"""``restore CLIP --temporal N --deblur physics`` without ``--dr0`` measures D/r0 on the clip's first frames and then
restores the clip: each frame is decoded once (the measured frames are kept and given to the restorer again), counted
by wrappers around the readers themselves, for a folder of frames and a video."""

import json

import cv2
import numpy as np
import pytest
import torch

from d2turb.sim import Simulator, TurbulenceParams

LAM, APERTURE, Q, FRAMES = 525e-9, 0.1, 2.0, 12


def _clip() -> tuple[list[np.ndarray], float]:
    """Simulated turbulence over a textured scene (D/r0 2.5): 8-bit RGB frames, and the camera's ifov."""
    from skimage import data, transform

    ifov = LAM / (APERTURE * Q)
    p = TurbulenceParams(aperture_m=APERTURE, wavelength_m=LAM, path_length_m=1000.0, dr0=2.5, ifov_rad=ifov)
    scene = transform.resize(data.camera()[:384, :384], (112, 112), anti_aliasing=True)
    scene = torch.from_numpy(np.repeat(scene[None], 3, 0)).float()
    seq = Simulator(p).sequence(scene, frames=FRAMES, wind=2.0, boil=0.1, generator=torch.Generator().manual_seed(3))
    frames = [(r.turb[0].clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8) for r in seq]
    return frames, p.ifov_rad


def _restore(src, out, ifov, status: int = 0) -> dict:
    from d2turb.cli import main

    argv = ["restore", str(src), "--temporal", "4", "--deblur", "physics", "--ifov", repr(ifov), "--out", str(out)]
    assert main([*argv, "--path-length", "1000"]) == status
    return json.loads((out / "restore.json").read_text())


def _measured_on_all(record: dict) -> None:
    deblur = record["deblur"]
    assert record["frames"] == FRAMES and deblur["method"] == "physics"
    assert deblur["dr0_source"].startswith(f"measured on the clip's first {FRAMES} frames"), deblur["dr0_source"]


@pytest.mark.slow
def test_a_folder_clip_measured_for_the_physics_deblur_is_read_once(tmp_path, monkeypatch, capsys):
    """... and a bad frame among the measured ones is reported once (exit status 1: some inputs failed)."""
    from d2turb.io import folder

    frames, ifov = _clip()
    (tmp_path / "clip").mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / "clip" / f"{i:03d}.png"), f[..., ::-1])
    (tmp_path / "clip" / "005x.png").write_bytes(b"not a png")
    reads: dict[str, int] = {}
    real_read = folder.read_stored

    def counting_read(path):
        reads[path.name] = reads.get(path.name, 0) + 1
        return real_read(path)

    monkeypatch.setattr(folder, "read_stored", counting_read)
    _measured_on_all(_restore(tmp_path / "clip", tmp_path / "out", ifov, status=1))
    assert reads == {**{f"{i:03d}.png": 1 for i in range(FRAMES)}, "005x.png": 1}
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "005x.png" in errors[0], errors
    assert len(list((tmp_path / "out").glob("*_restored.png"))) == FRAMES


@pytest.mark.slow
def test_a_video_clip_measured_for_the_physics_deblur_is_decoded_once(tmp_path, monkeypatch):
    pytest.importorskip("av")
    from d2turb import video
    from d2turb.restore import clip_source

    frames, ifov = _clip()
    with video.Mp4Writer(tmp_path / "clip.mp4", 25.0) as writer:
        for f in frames:
            writer.write(f)
    decoded = {"opened": 0, "frames": 0}

    class CountingSource(video.VideoSource):
        def __init__(self, *args, **kwargs):
            decoded["opened"] += 1
            super().__init__(*args, **kwargs)

        def __iter__(self):
            for frame in super().__iter__():
                decoded["frames"] += 1
                yield frame

    monkeypatch.setattr(clip_source, "VideoSource", CountingSource)
    _measured_on_all(_restore(tmp_path / "clip.mp4", tmp_path / "out", ifov))
    assert decoded == {"opened": 1, "frames": FRAMES}
