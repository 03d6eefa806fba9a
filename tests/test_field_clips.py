"""Field-realistic clips (make-dataset --profile field, d2turb.data.field): the recorded shake is the displacement
phase correlation measures, the recorded object boxes hold the pasted patches, a dataset made with the profile reads
back with a truth per frame, and evaluate --clips scores it inside the boxes."""

import json

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage.registration import phase_cross_correlation

from d2turb.data.field import FIELD_RANGES, draw_clip, frame_point, render_scene, window_margin


def _texture(size: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.stack([ndimage.gaussian_filter(rng.random((size, size)), 2.0) for _ in range(3)], -1)
    return ((img - img.min()) / (img.max() - img.min())).astype(np.float32)


def test_recorded_shake_is_the_displacement_phase_correlation_measures():
    data = pytest.importorskip("skimage.data")
    patch, frames = 128, 9
    m = window_margin(patch)
    rng = np.random.default_rng(5)
    dx = np.concatenate([[0], rng.uniform(-6, 6, frames - 1)])
    dy = np.concatenate([[0], rng.uniform(-6, 6, frames - 1)])
    shake = {"dx_px": dx.tolist(), "dy_px": dy.tolist(), "rot_deg": [0.0] * frames}
    scene = data.astronaut()[50 : 50 + patch + 2 * m, 100 : 100 + patch + 2 * m].astype(np.float32) / 255
    clip, _, _ = render_scene(scene, [], shake, patch)
    grey = clip.mean(-1).astype(np.float64)
    hann = np.outer(np.hanning(patch), np.hanning(patch))
    for t in range(1, frames):
        a, b = (grey[t] - grey[t].mean()) * hann, (grey[0] - grey[0].mean()) * hann
        shift, _, _ = phase_cross_correlation(a, b, upsample_factor=100)  # (dy, dx) of frame t from frame 0
        # 0.2 px: the Hann-windowed phase correlation's error on a 6-px shift of a non-periodic scene (content
        # enters and leaves the window)
        assert shift[1] == pytest.approx(dx[t], abs=0.2)
        assert shift[0] == pytest.approx(dy[t], abs=0.2)


def test_rotation_and_translation_move_a_point_where_recorded():
    patch = 96
    m = window_margin(patch)
    window = np.zeros((patch + 2 * m, patch + 2 * m, 3), np.float32)
    px, py = 20.0, 70.0  # a bright dot in frame-0 coordinates
    yy, xx = np.mgrid[: window.shape[0], : window.shape[1]]
    window[..., :] = np.exp(-((xx - m - px) ** 2 + (yy - m - py) ** 2) / (2 * 1.5**2))[..., None]
    shake = {"dx_px": [0.0, 3.3, -4.2], "dy_px": [0.0, -2.1, 5.5], "rot_deg": [0.0, 1.2, -1.5]}
    clip, _, _ = render_scene(window, [], shake, patch)
    for t in range(3):
        cy, cx = ndimage.center_of_mass(clip[t, ..., 0])
        ex, ey = frame_point(px, py, shake["dx_px"][t], shake["dy_px"][t], shake["rot_deg"][t], patch)
        assert (cx, cy) == pytest.approx((ex, ey), abs=0.05)


def test_object_box_holds_the_pasted_patch():
    patch, frames = 128, 16
    draw = draw_clip(seed=3, index=7, frames=frames, patch=patch, fps=30.0, n_sources=5, scene_source=0)
    m = window_margin(patch)
    black = np.zeros((patch + 2 * m, patch + 2 * m, 3), np.float32)
    objects = [(obj, np.ones((obj["size"][1], obj["size"][0], 3), np.float32)) for obj in draw["objects"]]
    assert objects and all(obj["source"] != 0 for obj, _ in objects)  # patches of other images than the scene's
    clip, _, boxes = render_scene(black, objects, draw["shake"], patch)
    for k in range(len(objects)):
        one, _, _ = render_scene(black, [objects[k]], draw["shake"], patch)
        for t in range(frames):
            painted = one[t, ..., 0] > 1e-3
            box = boxes[k][t]
            if box is None:
                assert not painted.any()
                continue
            x0, y0, x1, y1 = box
            inside = np.zeros_like(painted)
            inside[y0:y1, x0:x1] = True
            assert not (painted & ~inside).any(), (t, box)
            ys, xs = np.nonzero(painted)
            assert len(ys)  # the box is no wider than the patch plus a pixel of interpolation on each side
            assert xs.min() - x0 <= 2 and ys.min() - y0 <= 2 and x1 - 1 - xs.max() <= 2 and y1 - 1 - ys.max() <= 2


def test_draws_stay_in_their_documented_ranges():
    r = FIELD_RANGES
    for i in range(40):
        d = draw_clip(seed=1, index=i, frames=48, patch=256, fps=30.0, n_sources=10, scene_source=i % 10)
        s, cam = d["shake"], d["camera"]
        assert max(map(abs, s["dx_px"] + s["dy_px"])) <= r["max_shift_frac"] * 256 + 1e-9
        assert max(map(abs, s["rot_deg"])) <= r["max_rot_deg"] + 1e-9
        assert r["objects"][0] <= len(d["objects"]) <= r["objects"][1]
        assert r["shot_gain"][0] <= cam["shot_gain"] <= r["shot_gain"][1]
        assert cam["codec"] in r["codecs"]
        if cam["codec"] == "jpeg":
            assert r["jpeg_quality"][0] <= cam["jpeg_quality"] <= r["jpeg_quality"][1]
        else:
            assert r["video_bpp"][0] <= cam["bpp"] <= r["video_bpp"][1]
        assert d == draw_clip(seed=1, index=i, frames=48, patch=256, fps=30.0, n_sources=10, scene_source=i % 10)


@pytest.fixture(scope="module")
def field_set(tmp_path_factory):
    pytest.importorskip("av")
    from d2turb.data.generate import DatasetConfig, generate_dataset
    from d2turb.io import write_image

    tmp = tmp_path_factory.mktemp("field")
    clean = tmp / "clean"
    for i in range(3):
        write_image(clean / f"img{i}.png", torch.from_numpy(_texture(80, seed=i)).permute(2, 0, 1))
    cfg = DatasetConfig(
        clean=[str(clean)],
        out=str(tmp / "ds"),
        pairs=3,
        patch=48,
        split="test",
        depth="none",
        seed=4,
        batch=1,
        device="cpu",
        frames=4,
        sequence={"fps": 30.0, "wind": 2.0},
        profile="field",
    )
    generate_dataset(cfg, progress=False)
    return tmp / "ds"


def test_a_field_dataset_reads_back_with_a_truth_per_frame_and_boxes(field_set):
    from d2turb.data import SequenceDataset, check_dataset

    assert check_dataset(field_set).ok
    config = json.loads((field_set / "dataset.json").read_text())
    assert config["profile"] == "field" and config["field"] == json.loads(json.dumps(FIELD_RANGES))
    data = SequenceDataset(field_set)
    item = data[0]
    assert item["turb"].shape == item["gt"].shape == (4, 3, 48, 48)
    record = data.records[0]
    boxes = item["boxes"]
    assert boxes.shape == (4, len(record["field"]["objects"]), 4)
    assert record["field"]["camera"]["codec"] in FIELD_RANGES["codecs"]
    # frame 0 has pose 0: outside the objects' boxes its truth is the crop at the window's centre, decoded, exposed,
    # clipped at saturation and encoded again (IEC 61966-2-1 written out here)
    shake = record["field"]["shake"]
    assert shake["dx_px"][0] == shake["dy_px"][0] == shake["rot_deg"][0] == 0.0
    from d2turb.io import read_image

    src = read_image(record["source"]).double()
    x0, y0, _, _ = record["crop"]
    m = window_margin(48)
    crop = src[:, y0 + m : y0 + m + 48, x0 + m : x0 + m + 48]
    lin = torch.where(crop <= 0.04045, crop / 12.92, ((crop + 0.055) / 1.055) ** 2.4)
    lin = (lin * record["field"]["camera"]["exposure"]).clamp(0, 1)
    expected = torch.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    outside = torch.ones(48, 48, dtype=torch.bool)
    for bx0, by0, bx1, by1 in boxes[0].tolist():
        if bx0 >= 0:
            outside[by0:by1, bx0:bx1] = False
    assert outside.sum() > 100
    assert float((item["gt"][0] - expected).abs()[:, outside].max()) <= 0.5 / 255 + 1e-4


def test_evaluate_scores_field_clips_inside_the_boxes(field_set, tmp_path):
    from d2turb.eval.clips import box_psnr, evaluate_clips

    results = evaluate_clips(
        field_set, tmp_path / "ev", deblur=["none"], temporal=4, stride=2, max_samples=2, progress=False
    )
    for stats in results["bins"].values():
        for row in ("input", "fused"):
            assert np.isfinite(stats[f"{row} psnr_aligned"])
    assert any("input box_psnr_aligned" in s for s in results["samples"])
    assert "Inside the moving objects' boxes" in (tmp_path / "ev" / "results.md").read_text()
    ref = torch.zeros(3, 20, 20)
    img = ref.clone()
    img[:, 2:10, 2:10] = 0.1  # MSE 0.01 inside the box, 0 outside
    assert box_psnr(img, ref, [2, 2, 10, 10]) == pytest.approx(20.0, abs=1e-6)
    assert box_psnr(img, ref, [0, 0, 4, 4]) is None  # under MIN_BOX_PX pixels
