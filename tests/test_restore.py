"""Tiled restoration (d2turb.restore): equality with untiled inference, absence of seams, weights lookup."""

import math

import pytest
import torch
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.ops import warp
from d2turb.restore import Restorer, axis_window, resolve_weights, tile_starts, warp_in_strips, weights_search_path


class LocalModel(nn.Module):
    """Fully convolutional stand-in with a small receptive field (two 3x3 convs: radius 2 px), a
    nonzero flow head (|flow| up to 3 px) and restored = warp(deblurred, flow), as in Eq. 9."""

    def __init__(self, seed=0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.a = nn.Conv2d(3, 8, 3, padding=1)
        self.b = nn.Conv2d(8, 5, 3, padding=1)
        for p in self.parameters():
            p.data = torch.randn(p.shape, generator=g) * 0.3

    def forward(self, x):
        h = self.b(torch.tanh(self.a(x)))
        deblurred = (x + 0.1 * torch.tanh(h[:, :3])).clamp(0, 1)
        flow = 3.0 * torch.tanh(h[:, 3:])
        return {"deblurred": deblurred, "restored": warp(deblurred, flow), "flow": flow, "guide": None}


class PerTileOffset(nn.Module):
    """A maximally non-local model: adds a constant that depends on the tile's mean, so neighbouring tiles
    disagree by a known jump. Hard stitching would show that jump as a seam; blending must not."""

    def forward(self, x):
        y = x * 0 + 0.5 + 0.3 * torch.tanh(20 * (x.mean() - 0.5))
        return {"deblurred": y, "restored": y, "flow": torch.zeros_like(x[:, :2]) + 2.0 * y[:, :2], "guide": None}


@pytest.fixture
def photo(astronaut):
    # 256x256 sample tiled to a non-square 300x420 image with natural content everywhere
    wide = torch.cat([astronaut, astronaut.flip(-1)], dim=3)
    return torch.cat([wide, wide.flip(-2)], dim=2)[0, :, 20:320, :420].contiguous()


def test_tile_layout_covers_image_with_overlap():
    for length, tile, overlap in [(1000, 256, 32), (257, 256, 32), (256, 256, 32), (100, 256, 32), (700, 128, 64)]:
        starts = tile_starts(length, tile, overlap)
        size = min(tile, length)
        assert starts[0] == 0 and starts[-1] + size == length
        assert all(b - a <= tile - overlap for a, b in zip(starts, starts[1:]))  # shared >= overlap
    w = axis_window(64, 16, True, True)
    assert w.min() > 0 and w.max() == 1 and torch.allclose(w, w.flip(0))
    assert w[:4].max() < 1e-5 and w[:4].min() > 0  # guard band at the tile edge: tiny but positive weight
    # complementary ramps: two tiles overlapping by exactly `overlap` sum to 1 (partition of unity)
    a, b = axis_window(64, 16, False, True), axis_window(64, 16, True, False)
    torch.testing.assert_close(a[-16:] + b[:16], torch.ones(16), atol=1e-5, rtol=0)


def test_strip_warp_equals_one_shot_warp(monkeypatch):
    import d2turb.restore.single as r

    monkeypatch.setattr(r, "_WARP_STRIP_PIXELS", 7 * 50)  # force many 7-row strips
    g = torch.Generator().manual_seed(1)
    img, flow = torch.rand(1, 3, 40, 50, generator=g), 6 * torch.randn(1, 2, 40, 50, generator=g)
    torch.testing.assert_close(warp_in_strips(img, flow), warp(img, flow), atol=1e-6, rtol=0)


def test_untiled_equals_model(photo):
    model = LocalModel()
    got = Restorer(model, tile=1024).restore_with_details(photo)
    ref = model(photo[None])
    torch.testing.assert_close(got["restored"], ref["restored"][0].clamp(0, 1), atol=1e-5, rtol=0)
    torch.testing.assert_close(got["bwd_flow_px"], ref["flow"][0], atol=1e-6, rtol=0)  # a model naming it "flow"
    assert set(got) == {"restored", "deblurred", "bwd_flow_px"}  # one key per tensor
    with pytest.warns(DeprecationWarning, match="bwd_flow_px"):
        assert got["flow"] is got["bwd_flow_px"]  # the deprecated name


def _boundary_columns(length, tile, overlap):
    """Tile edge positions along an axis (where a tile starts or ends inside the image)."""
    edges = set()
    for s in tile_starts(length, tile, overlap):
        edges.update(e for e in (s, s + tile) if 0 < e < length)
    return sorted(edges)


def test_tiled_equals_untiled_and_has_no_seam(photo):
    model, tile, overlap = LocalModel(), 128, 32
    full = Restorer(model, tile=1024).restore_with_details(photo)
    tiled = Restorer(model, tile=tile, overlap=overlap).restore_with_details(photo)
    for key in ("restored", "deblurred", "bwd_flow_px"):
        diff = (tiled[key] - full[key]).abs()
        # the receptive field (2 px) is far inside the overlap, so tiles agree with the untiled model everywhere
        assert diff.mean() < 1e-4, key
        assert diff.max() < 1e-3, key
    # no seam: the difference map has no structure at tile edges (its energy there is no larger than elsewhere)
    d = (tiled["restored"] - full["restored"]).abs().mean(0)
    cols = _boundary_columns(photo.shape[2], tile, overlap)
    assert d[:, cols].mean() <= d.mean() + 1e-5


def test_blending_hides_tile_disagreement(astronaut):
    """Tiles whose outputs jump by Δ are blended with the raised-cosine ramp: the largest step between
    neighbouring pixels is ≤ Δ·π/overlap (the ramp's maximum slope), never the hard-stitch jump Δ."""
    img = torch.cat([astronaut[0], astronaut[0].flip(-1)], dim=2)  # 256x512: tiles with different means
    tile, overlap = 128, 32
    out = Restorer(PerTileOffset(), tile=tile, overlap=overlap).restore_with_details(img)
    deb = out["deblurred"][0]
    # per-tile constants, measured by running the model on each tile alone
    consts = [
        float(PerTileOffset()(img[None, :, y : y + tile, x : x + tile])["deblurred"].mean())
        for y in tile_starts(256, tile, overlap)
        for x in tile_starts(512, tile, overlap)
    ]
    jump = max(consts) - min(consts)
    assert jump > 0.1  # the tiles really disagree
    steps = max(deb.diff(dim=0).abs().max(), deb.diff(dim=1).abs().max())
    assert steps <= jump * math.pi / overlap * 1.05 + 1e-4
    assert out["bwd_flow_px"].isfinite().all() and out["restored"].isfinite().all()


def test_shapes_batch_and_path(tmp_path, photo):
    from d2turb.io import write_image

    r = Restorer("input")
    assert torch.equal(r.restore(photo), photo)  # identity baseline returns its input exactly
    batch = torch.stack([photo, photo.flip(-1)])
    out = Restorer(LocalModel(), tile=128, overlap=32).restore_with_details(batch)
    assert out["restored"].shape == batch.shape and out["bwd_flow_px"].shape == (2, 2, 300, 420)
    write_image(tmp_path / "p.png", photo)
    assert r.restore(tmp_path / "p.png").shape == (3, 300, 420)


def test_bad_arguments_raise_one_line_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("D2TURB_WEIGHTS_DIR", str(tmp_path))
    with pytest.raises(D2TurbError, match="not found; looked in: .*" + str(tmp_path).replace("\\", "\\\\")):
        resolve_weights("no-such-model")
    with pytest.raises(D2TurbError, match="weights file not found"):
        resolve_weights(str(tmp_path / "missing.safetensors"))
    (tmp_path / "old.pth").write_bytes(b"x")
    with pytest.raises(D2TurbError, match="only .safetensors") as info:
        resolve_weights(str(tmp_path / "old.pth"))
    assert f"d2turb convert {tmp_path / 'old.pth'} {tmp_path / 'old.safetensors'}" in str(info.value)
    (tmp_path / "mine.safetensors").write_bytes(b"x")
    assert resolve_weights("mine") == tmp_path / "mine.safetensors"
    assert weights_search_path("mine")[0] == tmp_path / "mine.safetensors"
    (tmp_path / "v1.2.safetensors").write_bytes(b"x")
    assert resolve_weights("v1.2") == tmp_path / "v1.2.safetensors"  # dotted names are names, not paths
    with pytest.raises(D2TurbError, match="'nafnet-gpu-spectral' no longer ship with d2turb: .*nafnet-gpu-spectral3"):
        resolve_weights("nafnet-gpu-spectral")  # retired: the reason, not "not found"
    (tmp_path / "nafnet-gpu-spectral.safetensors").write_bytes(b"x")
    assert resolve_weights("nafnet-gpu-spectral") == tmp_path / "nafnet-gpu-spectral.safetensors"  # a kept copy
    with pytest.raises(D2TurbError, match="overlap"):
        Restorer("input", tile=64, overlap=40)
    with pytest.raises(D2TurbError, match="expected 3 channels"):
        Restorer("input").restore(torch.rand(1, 4, 8, 8))
    with pytest.raises(D2TurbError, match="NaN"):
        Restorer("input").restore(torch.full((3, 8, 8), float("nan")))
    if not torch.cuda.is_available():
        with pytest.raises(D2TurbError, match="CUDA is not available"):
            Restorer("input", device="cuda")


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
