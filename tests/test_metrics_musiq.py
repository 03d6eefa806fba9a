"""MUSIQ (d2turb.eval.musiq): tiny random models saved/loaded with pyiqa key names, preprocessing by hand."""

import math
import os
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from d2turb.errors import D2TurbError
from d2turb.eval.musiq import (
    MUSIQ,
    MUSIQConfig,
    extract_patches,
    hashed_position_index,
    multiscale_patches,
    musiq,
    resized_size,
)

TINY = MUSIQConfig(hidden_size=32, num_layers=2, num_heads=2, mlp_dim=64, stem_width=32)
PYIQA_KONIQ_PARAMS = 27_125_825  # published config, 1-output head; the released .pth is 108,610,983 bytes
USER_WEIGHTS = os.environ.get("D2TURB_MUSIQ_WEIGHTS")  # read before the fixture below hides it
# IQA-PyTorch ResultsCalibra/calibration_summary.csv, "(ours)" rows = pyiqa's torch port that d2turb follows
# (the official TF scores differ by up to ~1.4 points, e.g. koniq I19: 36.938)
PYIQA_GOLDEN = {
    "koniq": (12.4773, 75.7764, 73.7459, 75.4604, 38.0248),
    "spaq": (17.6804, 70.6531, 79.0364, 79.3189, 50.4526),
    "paq2piq": (46.0187, 72.6657, 73.7655, 74.388, 69.7218),
    "ava": (3.4084, 5.6934, 4.6968, 5.1963, 4.1955),
}


@pytest.fixture(autouse=True)
def _no_user_weights(monkeypatch, tmp_path):
    torch.set_num_threads(1)  # small matmuls: 2 threads on the shared 2-core box are up to 15x slower under load
    monkeypatch.delenv("D2TURB_MUSIQ_WEIGHTS", raising=False)
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(tmp_path / "empty_cache"))


def _tiny(num_classes=1, seed=0):
    torch.manual_seed(seed)
    return MUSIQ(weights=False, config=MUSIQConfig(**{**TINY.__dict__, "num_classes": num_classes}))


@pytest.fixture
def tiny_file(tmp_path):
    model = _tiny()
    path = tmp_path / "musiq_koniq_ckpt-e95806b9.pth"
    torch.save(model.state_dict(), path)
    return model, path


def _images(n=2, h=40, w=56, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, h, w, generator=g)


# ----------------------------------------------------------------------------- loading


def test_loads_by_argument_env_file_env_folder_and_cache(tiny_file, monkeypatch, tmp_path):
    reference, path = tiny_file
    image = _images(1)
    expected = reference(image)
    assert torch.equal(MUSIQ(path, config=TINY)(image), expected)
    monkeypatch.setenv("D2TURB_MUSIQ_WEIGHTS", str(path))
    assert torch.equal(MUSIQ(config=TINY)(image), expected)
    monkeypatch.setenv("D2TURB_MUSIQ_WEIGHTS", str(path.parent))
    assert torch.equal(MUSIQ(config=TINY)(image), expected)
    monkeypatch.delenv("D2TURB_MUSIQ_WEIGHTS")
    cache = tmp_path / "cache"
    (cache / "musiq").mkdir(parents=True)
    path.rename(cache / "musiq" / "musiq_koniq_ckpt-e95806b9.pth")
    monkeypatch.setenv("D2TURB_CACHE_DIR", str(cache))
    assert torch.equal(MUSIQ(config=TINY)(image), expected)


def test_safetensors_and_module_prefix_are_accepted(tmp_path):
    from safetensors.torch import save_file

    model = _tiny()
    image = _images(1)
    save_file(model.state_dict(), tmp_path / "m.safetensors")
    torch.save({f"module.{k}": v for k, v in model.state_dict().items()}, tmp_path / "m.pth")
    assert torch.equal(MUSIQ(tmp_path / "m.safetensors", config=TINY)(image), model(image))
    assert torch.equal(MUSIQ(tmp_path / "m.pth", config=TINY)(image), model(image))


def _one_line_error(fn) -> str:
    with pytest.raises(D2TurbError) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message
    return message


def test_missing_weights_are_one_line_errors(tmp_path, monkeypatch):
    message = _one_line_error(lambda: MUSIQ(tmp_path / "nope.pth"))
    assert "nope.pth" in message and "not found" in message
    message = _one_line_error(lambda: MUSIQ())
    assert "D2TURB_MUSIQ_WEIGHTS" in message and "musiq_koniq_ckpt-e95806b9.pth" in message and "download" in message
    monkeypatch.setenv("D2TURB_MUSIQ_WEIGHTS", str(tmp_path / "missing_dir" / "x.pth"))
    assert "x.pth" in _one_line_error(lambda: MUSIQ())


def test_wrong_files_are_one_line_errors(tiny_file, tmp_path):
    _, tiny_path = tiny_file
    other = tmp_path / "alexnet.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 11, 11)}, other)
    assert "not a MUSIQ checkpoint" in _one_line_error(lambda: MUSIQ(other))
    # the right keys, minus one, plus a foreign one
    state = _tiny().state_dict()
    state.pop("transformer_encoder.cls")
    state["extra.weight"] = torch.zeros(1)
    broken = tmp_path / "broken.pth"
    torch.save(state, broken)
    message = _one_line_error(lambda: MUSIQ(broken, config=TINY))
    assert "transformer_encoder.cls" in message and "extra.weight" in message
    # a tiny checkpoint is not the published size
    assert "192 missing keys" in _one_line_error(lambda: MUSIQ(tiny_path))
    wider = MUSIQConfig(**{**TINY.__dict__, "hidden_size": 48})
    message = _one_line_error(lambda: MUSIQ(tiny_path, config=wider))
    assert "wrong shape" in message and "embedding.weight is (32, 8192) in the file" in message
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a torch file")
    assert "cannot load" in _one_line_error(lambda: MUSIQ(garbage))


# ----------------------------------------------------------------------------- behaviour


def test_scores_shape_determinism_finiteness_and_sensitivity(tiny_file):
    _, path = tiny_file
    model = MUSIQ(path, config=TINY)
    images = _images(3)
    scores = model(images)
    assert scores.shape == (3,) and torch.isfinite(scores).all()
    assert torch.equal(model(images), scores)
    singles = torch.stack([model(im) for im in images])[:, 0]
    torch.testing.assert_close(singles, scores, rtol=0, atol=1e-5)
    assert (scores[:, None] - scores[None, :]).abs().triu(1).max() > 1e-4  # different images, different scores
    assert model(images[0]).shape == (1,)
    assert "3 channels" in _one_line_error(lambda: model(torch.rand(1, 4, 40, 40)))
    assert "NaN" in _one_line_error(lambda: model(torch.full((1, 3, 40, 40), float("nan"))))
    assert model(torch.rand(1, 3, 2, 500)).isfinite().all()  # 224-scale height rounds to 1 row


def test_ava_head_is_the_mean_of_the_10_way_distribution():
    model = _tiny(num_classes=10)
    probs = torch.tensor([0.05, 0.0, 0.1, 0.2, 0.3, 0.15, 0.1, 0.05, 0.05, 0.0]) + 1e-6
    probs = probs / probs.sum()
    with torch.no_grad():
        model.head[0].weight.zero_()
        model.head[0].bias.copy_(probs.log())
    expected = float((probs * torch.arange(1, 11)).sum())
    torch.testing.assert_close(model(_images(2)), torch.full((2,), expected), rtol=0, atol=1e-5)


def test_dropping_padding_equals_the_padded_masked_sequence_of_the_official_code():
    """pyiqa/official: each resized scale is padded to ceil(L/32)^2 tokens that are masked (-1e3) in attention."""
    model = _tiny()
    enc = model.transformer_encoder
    torch.manual_seed(3)
    n, pad = 12, 5
    tokens, spatial, scale = torch.randn(2, n, 32), torch.randint(0, 100, (n,)), torch.randint(0, 3, (n,))
    ours = enc(tokens, spatial, scale)[:, 0]

    x = torch.cat([tokens, torch.randn(2, pad, 32)], 1)  # padding tokens: position 0, scale 0, mask 0
    pos = torch.cat([spatial, torch.zeros(pad, dtype=torch.long)])
    sc = torch.cat([scale, torch.zeros(pad, dtype=torch.long)])
    mask = torch.cat([torch.ones(1 + n), torch.zeros(pad)])
    x = x + enc.posembed_input.position_emb[0, pos] + enc.scaleembed_input.scale_emb[sc]
    x = torch.cat([enc.cls.expand(2, -1, -1), x], 1)
    for block in enc.transformer.values():
        att, y = block.attention, block.norm1(x)
        heads = lambda t: t.reshape(2, -1, 2, 16).transpose(1, 2)  # noqa: E731
        logits = heads(att.query(y)) @ heads(att.key(y)).transpose(-1, -2) / math.sqrt(16)
        logits = logits.masked_fill((mask[:, None] * mask[None, :]) == 0, -1e3)
        y = (logits.softmax(-1) @ heads(att.value(y))).transpose(1, 2).reshape(2, -1, 32)
        x = x + att.out(y)
        x = x + block.mlp.fc2(F.gelu(block.mlp.fc1(block.norm2(x))))
    reference = enc.encoder_norm(x)[:, 0]
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-5)


# ----------------------------------------------------------------------------- preprocessing by hand


def test_multiscale_patches_match_a_hand_computation():
    image = torch.rand(1, 3, 50, 70) * 2 - 1
    patches, spatial, scale = multiscale_patches(image, MUSIQConfig())
    # 224: ratio 3.2 -> 160x224 -> 5x7 patches; 384: ratio 5.486 -> 274x384 -> 9x12; original 50x70 -> 2x3
    assert resized_size(50, 70, 224) == (160, 224) and resized_size(50, 70, 384) == (274, 384)
    assert patches.shape == (1, 35 + 108 + 6, 3, 32, 32)
    assert scale.tolist() == [0] * 35 + [1] * 108 + [2] * 6
    # hash onto the 10x10 grid: row floor(10 i / nh), column floor(10 j / nw)
    rows5, cols7 = [0, 2, 4, 6, 8], [0, 1, 2, 4, 5, 7, 8]
    assert spatial[:35].tolist() == [10 * r + c for r in rows5 for c in cols7]
    assert spatial[-6:].tolist() == [0, 3, 6, 50, 53, 56]
    # original scale: 64x96 after TF SAME padding, 7 rows / 13 columns of zeros before the image
    first, last = patches[0, 143], patches[0, 148]
    assert torch.equal(first[:, 7:, 13:], image[0, :, :25, :19])
    assert first[:, :7].abs().sum() == 0 and first[:, :, :13].abs().sum() == 0
    assert torch.equal(last[:, :25, :19], image[0, :, 25:, 51:])
    assert last[:, 25:].abs().sum() == 0 and last[:, :, 19:].abs().sum() == 0
    # resized scales are bicubic resizes of the whole image
    resized = F.interpolate(image, (160, 224), mode="bicubic", align_corners=False)
    assert torch.equal(patches[0, 8], resized[0, :, 32:64, 32:64])


def test_hash_index_matches_nearest_resizing_of_the_grid_as_in_pyiqa():
    for count_h, count_w in [(1, 1), (3, 7), (10, 10), (12, 25), (205, 31), (299, 2)]:
        grid = torch.arange(10.0)[None, None]
        rows = F.interpolate(grid, count_h, mode="nearest").flatten().long()
        cols = F.interpolate(grid, count_w, mode="nearest").flatten().long()
        assert torch.equal(hashed_position_index(count_h, count_w), (rows[:, None] * 10 + cols[None, :]).flatten())
    assert hashed_position_index(12, 1).tolist() == [0, 0, 10, 20, 30, 40, 50, 50, 60, 70, 80, 90]


def test_extract_patches_row_major_order_and_round_half_even():
    image = torch.arange(2 * 64 * 96, dtype=torch.float32).reshape(1, 2, 64, 96)
    patches, nh, nw = extract_patches(image, 32)
    assert (nh, nw) == (2, 3)
    for k in range(6):
        i, j = divmod(k, 3)
        assert torch.equal(patches[0, k], image[0, :, 32 * i : 32 * i + 32, 32 * j : 32 * j + 32])
    assert resized_size(3, 4, 6) == (4, 6)  # 4.5 -> 4 (tf.round / Python round: half to even)
    assert resized_size(5, 4, 6) == (6, 5)  # 4.8 -> 5


# ----------------------------------------------------------------------------- published configuration


def _pyiqa_key_shapes(num_classes=1):
    """pyiqa/archs/musiq_arch.py MUSIQ(): 384 hidden, 14 blocks, 6 heads, mlp 1152, stem 64, 3 scales, grid 10."""
    d, mlp = 384, 1152
    shapes = {"conv_root.weight": (64, 3, 7, 7), "gn_root.weight": (64,), "gn_root.bias": (64,)}
    for name, shape in [
        ("conv1", (64, 64, 1, 1)),
        ("conv2", (64, 64, 3, 3)),
        ("conv3", (256, 64, 1, 1)),
        ("conv_proj", (256, 64, 1, 1)),
    ]:
        shapes[f"block1.{name}.weight"] = shape
        gn = name.replace("conv", "gn")
        shapes[f"block1.{gn}.weight"] = shapes[f"block1.{gn}.bias"] = (shape[0],)
    shapes.update(
        {
            "embedding.weight": (d, 256 * 8 * 8),
            "embedding.bias": (d,),
            "transformer_encoder.cls": (1, 1, d),
            "transformer_encoder.posembed_input.position_emb": (1, 100, d),
            "transformer_encoder.scaleembed_input.scale_emb": (3, d),
            "transformer_encoder.encoder_norm.weight": (d,),
            "transformer_encoder.encoder_norm.bias": (d,),
        }
    )
    for i in range(14):
        p = f"transformer_encoder.transformer.encoderblock_{i}."
        for norm in ("norm1", "norm2"):
            shapes[p + norm + ".weight"] = shapes[p + norm + ".bias"] = (d,)
        for proj in ("query", "key", "value", "out"):
            shapes[f"{p}attention.{proj}.weight"], shapes[f"{p}attention.{proj}.bias"] = (d, d), (d,)
        shapes.update(
            {
                p + "mlp.fc1.weight": (mlp, d),
                p + "mlp.fc1.bias": (mlp,),
                p + "mlp.fc2.weight": (d, mlp),
                p + "mlp.fc2.bias": (d,),
            }
        )
    head = "head" if num_classes == 1 else "head.0"
    shapes.update({f"{head}.weight": (num_classes, d), f"{head}.bias": (num_classes,)})
    return shapes


@pytest.mark.parametrize("num_classes", [1, 10])
def test_published_config_has_the_pyiqa_keys_and_shapes(num_classes):
    with torch.device("meta"):
        model = MUSIQ(weights=False, device="meta", config=MUSIQConfig(num_classes=num_classes))
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert ours == _pyiqa_key_shapes(num_classes)
    assert len(ours) == 248
    n_params = sum(math.prod(s) for s in ours.values())
    assert n_params == PYIQA_KONIQ_PARAMS + (0 if num_classes == 1 else 9 * 385)
    # float32 payload 108,503,300 bytes; the released koniq .pth (108,610,983 bytes) adds ~0.1 MB of zip/pickle


def test_full_size_random_checkpoint_through_functional_and_evaluate_real(tmp_path, monkeypatch):
    from d2turb.eval import musiq as musiq_module
    from d2turb.eval.real import evaluate_real, no_reference_metric
    from d2turb.io import read_image, write_image

    torch.manual_seed(0)
    full = MUSIQ(weights=False)
    path = tmp_path / "musiq_koniq_ckpt-e95806b9.pth"
    torch.save(full.state_dict(), path)
    image = _images(1, 36, 44)[0]
    real = tmp_path / "real"
    write_image(real / "a.png", image)
    with torch.no_grad():
        expected, expected_png = full(image)[0], full(read_image(real / "a.png"))[0]
    del full  # loaded again from its file below: one full-size model (108 MB) at a time
    try:
        torch.testing.assert_close(musiq(image, weights=path), expected, rtol=0, atol=1e-6)
        monkeypatch.setenv("D2TURB_MUSIQ_WEIGHTS", str(path))
        score = no_reference_metric("musiq")
        assert isinstance(score(image), float)
        results = evaluate_real(real, ["musiq"], tmp_path / "out")
        stored = torch.tensor(results["musiq"]["per_image"]["a.png"])
        torch.testing.assert_close(stored, expected_png, rtol=0, atol=1e-5)
        assert "MUSIQ ↑" in (tmp_path / "out" / "results.md").read_text()
    finally:
        musiq_module._cached_model.cache_clear()  # the loaded model would stay for the rest of the session


@pytest.mark.skipif(
    not USER_WEIGHTS or not Path(USER_WEIGHTS).is_file(),
    reason="needs a real pyiqa checkpoint in D2TURB_MUSIQ_WEIGHTS (never downloaded)",
)
def test_real_checkpoint_matches_pyiqa_calibration_scores(shared_data):
    from d2turb.io import read_image

    variant = next((v for v in PYIQA_GOLDEN if v in Path(USER_WEIGHTS).name), None)
    if variant is None:
        pytest.skip(f"cannot tell the MUSIQ variant from {USER_WEIGHTS} (expects koniq/spaq/paq2piq/ava in the name)")
    model = MUSIQ(USER_WEIGHTS)
    names = ["I03", "I04", "I06", "I08", "I19"]
    scores = [float(model(read_image(shared_data / "iqa_calibration" / "dist" / f"{n}.png"))[0]) for n in names]
    tolerance = 0.01 if variant == "ava" else 0.1
    assert scores == pytest.approx(PYIQA_GOLDEN[variant], abs=tolerance)
