"""Acceptance 1 with a real (tiny, randomly initialised) D²Turb model: tiled == untiled, no seam."""

import numpy as np
import pytest
import torch

from d2turb.restore import Restorer, tile_starts

TILE, OVERLAP = 128, 32


@pytest.fixture(scope="module")
def tiny_model():
    from _tiny_models import tiny_d2turb

    # the flow head is zero-initialised (identity warp): nonzero so the warp matters (|V̂| ≈ 4-5 px), and the
    # NAFBlocks' residual gains switched on so their global channel attention is active too
    model = tiny_d2turb(flow_std=5.0)
    for name, p in model.named_parameters():
        if name.endswith(("beta", "gamma")):
            torch.nn.init.normal_(p, std=0.5)
    return model.eval()


@pytest.fixture(scope="module")
def photo():
    from skimage import data, transform

    a = torch.from_numpy(transform.resize(data.astronaut(), (256, 256), anti_aliasing=True)).float().permute(2, 0, 1)
    wide = torch.cat([a, a.flip(-1)], dim=2)
    return torch.cat([wide, wide.flip(-2)], dim=1)[:, 16:304, :416].contiguous()  # 288 x 416, 3 x 4 tiles


@pytest.fixture(scope="module")
def results(tiny_model, photo):
    with torch.no_grad():
        direct = tiny_model(photo[None])
    return {
        "direct": {k: direct[k][0] for k in ("restored", "deblurred", "bwd_flow_px")},
        "untiled": Restorer(tiny_model, tile=1024).restore_with_details(photo),
        "tiled": Restorer(tiny_model, tile=TILE, overlap=OVERLAP).restore_with_details(photo),
        "stitched": Restorer(tiny_model, tile=TILE, overlap=0).restore_with_details(photo),  # negative control
    }


def _tile_edges(length, overlap):
    edges = set()
    for s in tile_starts(length, TILE, overlap):
        edges.update(e for e in (s, s + TILE) if 0 < e < length)
    return sorted(edges)


def _edge_gradient_energy(x, overlap):
    """Mean |finite difference| across the lines where tiles start or end (x: (C, H, W))."""
    cols = [c - 1 for c in _tile_edges(x.shape[-1], overlap)]
    rows = [r - 1 for r in _tile_edges(x.shape[-2], overlap)]
    gx, gy = x.diff(dim=-1).abs(), x.diff(dim=-2).abs()
    return float(gx[..., cols].mean()), float(gy[..., rows, :].mean())


def test_untiled_restorer_is_the_model(results):
    assert results["direct"]["bwd_flow_px"].abs().mean() > 2  # the warp really moves pixels
    for key in ("restored", "deblurred", "bwd_flow_px"):
        ref = results["direct"][key].clamp(0, 1) if key != "bwd_flow_px" else results["direct"][key]
        torch.testing.assert_close(results["untiled"][key], ref, atol=2e-4, rtol=0)


def test_tiled_equals_untiled_away_from_borders(results):
    band = 8  # exclude the image border, where the untiled model pads the 288x416 image to its multiple of 8
    for key in ("restored", "deblurred", "bwd_flow_px"):
        diff = (results["tiled"][key] - results["untiled"][key]).abs()[:, band:-band, band:-band]
        assert diff.mean() < 1e-3, (key, float(diff.mean()))


def test_no_seam_at_tile_edges(results):
    """Across every tile edge, the tiled output's gradient energy equals the untiled output's at the same
    lines (within 2 %), and the tiled−untiled difference map is no larger there than elsewhere. The hard
    stitched control (overlap 0) shows how a seam registers on the same measure."""
    for key in ("restored", "bwd_flow_px"):
        tiled, untiled = results["tiled"][key], results["untiled"][key]
        for got, ref in zip(_edge_gradient_energy(tiled, OVERLAP), _edge_gradient_energy(untiled, OVERLAP)):
            assert got <= 1.02 * ref + 1e-5, key
        diff = (tiled - untiled).abs().mean(0)
        cols = _tile_edges(diff.shape[1], OVERLAP)
        band = torch.cat([diff[:, max(c - 2, 0) : c + 2] for c in cols], dim=1)
        assert band.mean() <= 2 * diff.mean() + 1e-5, key
    stitched, untiled = results["stitched"]["bwd_flow_px"], results["untiled"]["bwd_flow_px"]
    got, ref = _edge_gradient_energy(stitched, 0), _edge_gradient_energy(untiled, 0)
    assert got[0] > 5 * ref[0] and got[1] > 5 * ref[1]  # the measure does detect a real seam


def test_cli_with_saved_weights_matches_api(tmp_path, tiny_model, photo, monkeypatch):
    from d2turb.cli import main
    from d2turb.io import read_image, write_image
    from d2turb.models import save_pretrained

    save_pretrained(tiny_model, tmp_path / "tiny.safetensors")
    small = photo[:, :100, :150].contiguous()
    write_image(tmp_path / "img.png", small)
    monkeypatch.setenv("D2TURB_WEIGHTS_DIR", str(tmp_path))
    rc = main(
        [
            "restore",
            str(tmp_path / "img.png"),
            "--weights",
            "tiny",
            "--out",
            str(tmp_path / "o"),
            "--tile",
            "64",
            "--overlap",
            "16",
            "--save-flow",
            "--save-intermediate",
        ]
    )
    assert rc == 0
    api = Restorer(str(tmp_path / "tiny.safetensors"), tile=64, overlap=16).restore_with_details(
        read_image(tmp_path / "img.png")
    )
    assert (read_image(tmp_path / "o" / "img_restored.png") - api["restored"]).abs().max() <= 0.5 / 255 + 1e-4
    assert (read_image(tmp_path / "o" / "img_deblurred.png") - api["deblurred"]).abs().max() <= 0.5 / 255 + 1e-4
    np.testing.assert_allclose(np.load(tmp_path / "o" / "img_bwd_flow_px.npy"), api["bwd_flow_px"].numpy(), atol=1e-5)
