"""The clip room's shape: the fusion registry, the deblur's boundary, the state made afresh per clip, and threads that
change when a stage runs, never what it computes."""

import numpy as np
import pytest
import torch

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.clip.fusion import FUSION_REGISTRY, Fusion, make_fusion, register_fusion
from d2turb.defaults import CLIP_FUSIONS
from d2turb.errors import D2TurbError


def _clip(seed: int, n: int = 12, size: int = 40) -> list[np.ndarray]:
    """A smooth random scene under a small random translation per frame, 8-bit as a camera stores it."""
    import cv2

    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.random((size + 16, size + 16, 3)).astype(np.float32), (0, 0), 1.5)
    frames = []
    for _ in range(n):
        dx, dy = rng.normal(0, 0.7, 2)
        m = np.float32([[1, 0, 8 + dx], [0, 1, 8 + dy]])
        f = cv2.warpAffine(base, m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        frames.append(np.rint(np.clip(f, 0, 1) * 255).astype(np.uint8))
    return frames


def test_the_registry_holds_the_fusions_the_command_line_offers():
    assert tuple(FUSION_REGISTRY) == CLIP_FUSIONS
    assert all(make_fusion(name).name == name for name in CLIP_FUSIONS)
    with pytest.raises(D2TurbError, match="unknown fusion"):
        make_fusion("nope")
    with pytest.raises(D2TurbError, match="unknown fusion"):
        ClipRestorer(fusion="nope")


def test_a_registered_fusion_is_used_by_name():
    """A fusion added from outside (the window's first frame, as registered) is chosen by its name; on frames that
    are all the same its output is that frame (identity: no other code path could give it)."""

    @register_fusion
    class FirstFrame(Fusion):
        name = "first-test"
        reads_mean = False

        def fuse(self, window, mean):
            first = next(iter(window.values())).warped[-1]
            return first.astype(np.float32) / (255 if first.dtype == np.uint8 else 1)

    try:
        frame = _clip(1, n=1)[0]
        out = list(ClipRestorer(temporal=4, fusion="first-test", stabilise=False).restore([frame] * 6))
        assert len(out) == 6
        for o in out:
            assert torch.equal(o.restored, torch.from_numpy(frame.astype(np.float32) / 255).permute(2, 0, 1))
    finally:
        FUSION_REGISTRY.pop("first-test")


@pytest.mark.parametrize("fusion", CLIP_FUSIONS)
@pytest.mark.parametrize("deblur", ["none", "physics"])
def test_threads_change_nothing(fusion, deblur):
    """The same clip with the stages overlapped in threads and run in the caller's thread: outputs equal to the bit."""
    frames = _clip(2)

    def run(threaded):
        d = "none" if deblur == "none" else PhysicsDeblur.for_fusion(2.0, 2.0, fusion)
        return list(ClipRestorer(temporal=5, fusion=fusion, deblur=d, threaded=threaded).restore(iter(frames)))

    a, b = run(True), run(False)
    assert [o.index for o in a] == list(range(len(frames))) == [o.index for o in b]
    for x, y in zip(a, b):
        assert torch.equal(x.restored, y.restored) and torch.equal(x.fused, y.fused)
        assert np.array_equal(x.bwd_flow_hwc_px, y.bwd_flow_hwc_px) and torch.equal(x.fallback, y.fallback)
        assert x.camera_px == y.camera_px


def test_each_clip_starts_afresh():
    """One restorer, two clips in a row: the second clip's outputs are those of a new restorer (no state carried)."""
    first, second = _clip(3), _clip(4)
    restorer = ClipRestorer(temporal=5, fusion="sharpest")
    list(restorer.restore(first))
    again = list(restorer.restore(second))
    fresh = list(ClipRestorer(temporal=5, fusion="sharpest").restore(second))
    for x, y in zip(again, fresh, strict=True):
        assert torch.equal(x.restored, y.restored)


def test_a_deblur_that_changes_the_shape_is_named_in_one_line():
    def cropping(fused):
        return fused[:, 1:, :]

    with pytest.raises(D2TurbError, match="must keep the shape"):
        list(ClipRestorer(temporal=4, deblur=cropping).restore(_clip(5, n=5)))
    with pytest.raises(D2TurbError, match="deblur must be"):
        ClipRestorer(deblur="sharpen")


@pytest.mark.parametrize("fusion", CLIP_FUSIONS)
def test_a_grey_clip_stays_grey_and_matches_the_colour_path(fusion):
    """A monochrome clip ((H,W,1) or (H,W) frames) comes out (1,H,W), and equal, to within a grey level, to each
    channel of the same clip given as colour with R = G = B (the colour path registers on the same luma). The
    sharpest fusion chooses by the amplitude √(Σ_c d_c²) rounded to 1/64 grey level, √3 times larger on three equal
    channels, so near-ties fall differently: its fused frames agree within a grey level (measured 0.86), and after
    the Wiener filter, which amplifies the difference, within two (measured 1.56)."""
    grey = [f.mean(axis=2).round().astype(np.uint8) for f in _clip(6, n=8, size=64)]
    colour = [np.repeat(g[..., None], 3, axis=2) for g in grey]
    deblur = PhysicsDeblur.for_fusion(2.0, 2.0, fusion)
    mono = list(ClipRestorer(temporal=5, fusion=fusion, deblur=deblur).restore(grey))
    rgb = list(ClipRestorer(temporal=5, fusion=fusion, deblur=deblur).restore(colour))
    levels = 2 if fusion == "sharpest" else 1
    for m, c in zip(mono, rgb, strict=True):
        assert m.restored.shape == (1, 64, 64) and c.restored.shape == (3, 64, 64)
        for ch in range(3):
            assert float((m.fused[0] - c.fused[ch]).abs().max()) <= 1 / 255 + 1e-6
            assert float((m.restored[0] - c.restored[ch]).abs().max()) <= levels / 255 + 1e-6


def test_the_tilt_spread_leaves_out_the_camera_roll_and_moving_objects():
    """A known field: a smooth random tilt of known rms, plus a camera roll of 0.5° and a shift (rigid), plus a patch
    moving 9 px (its fallback share 1): the spread read is the tilt's own rms (a 2 % tolerance: the rigid fit also
    takes the tilt's own small rotation); without the roll and the patch it is the rms about the mean, as trained."""
    import math

    import cv2

    from d2turb.clip.blur_net import TILT_SPREAD_FLOOR_PX, tilt_spread

    rng = np.random.default_rng(7)
    h, w = 192, 256
    tilt = np.stack([cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 12) for _ in range(2)])
    tilt -= tilt.mean((1, 2), keepdims=True)
    tilt *= 1.2 / np.sqrt((tilt**2).sum(0).mean())  # 1.2 px rms
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    theta = math.radians(0.5)
    rigid = np.stack([3.0 - theta * (y - (h - 1) / 2), -2.0 + theta * (x - (w - 1) / 2)])
    moving = np.zeros((h, w), np.float32)
    moving[40:80, 60:120] = 1
    flow = tilt + rigid + 9 * moving[None]

    def read(f, m=None):
        return math.exp(tilt_spread(f, m)) - TILT_SPREAD_FLOOR_PX

    assert read(flow, moving) == pytest.approx(1.2, rel=0.02)
    assert read(tilt) == pytest.approx(float(np.sqrt((tilt**2).sum(0).mean())), rel=0.02)
    assert read(flow) > 1.5  # the roll and the patch, left in, inflate it


def test_the_frame_standing_in_for_the_fusion_is_not_deblurred():
    """Where the single frame stands in for the fusion (a square crossing the scene: fallback share 1) the output is
    the fused frame itself; where the fusion is used (share 0) it is the deblur's; in between, their blend."""
    rng = np.random.default_rng(9)
    base = np.clip(0.5 + 0.1 * rng.standard_normal((64, 96, 3)), 0, 1).astype(np.float32)
    frames = []
    for i in range(8):
        f = base.copy()
        f[20:40, 8 + 10 * i : 28 + 10 * i] = [0.9, 0.1, 0.1]
        frames.append(f)

    def halve(fused):  # a "deblur" that changes every pixel
        return fused * 0.5

    outs = list(ClipRestorer(temporal=8, deblur=halve, tone_guard=False, stabilise=False).restore(frames))
    for o in outs:
        share = o.fallback[None]
        assert float(share.max()) > 0.99 and float(share.min()) == 0.0  # the square is found, the rest is fused
        expected = o.fused * 0.5 + (o.fused - o.fused * 0.5) * share
        assert torch.allclose(o.restored, expected, atol=1e-6)
        moving, still = share[0] > 0.99, share[0] == 0
        assert torch.allclose(o.restored[:, moving], o.fused[:, moving], atol=0.005)
        assert torch.equal(o.restored[:, still], o.fused[:, still] * 0.5)


def test_linear_light_deblurs_a_blur_of_light_better_and_leaves_a_model_alone():
    """Frames of a scene blurred in linear light (a Gaussian of 1.5 px, as air and optics blur it) and sRGB-encoded
    after: with ``linear_light`` the Wiener filter of that very blur restores the scene better than the same filter on
    the encoded values; a deblur without ``linear_light`` (a model) gets the frame as it is either way."""
    import cv2

    from d2turb.clip.blur import GaussianDeblur
    from d2turb.clip.deblur import deblur_in_linear_light
    from d2turb.sim.camera import linear_to_srgb, srgb_to_linear

    rng = np.random.default_rng(11)
    scene = torch.from_numpy(cv2.GaussianBlur(rng.random((96, 96, 3)).astype(np.float32), (0, 0), 1.0)).permute(2, 0, 1)
    scene = (scene - scene.min()) / (scene.max() - scene.min())
    light = srgb_to_linear(scene).permute(1, 2, 0).numpy()
    blurred = linear_to_srgb(torch.from_numpy(cv2.GaussianBlur(light, (0, 0), 1.5)).permute(2, 0, 1)).clamp(0, 1)

    class Wiener(GaussianDeblur):
        linear_light = True

    inner = (slice(None), slice(12, -12), slice(12, -12))

    def err(x):
        return float(((x - scene)[inner] ** 2).mean())

    encoded = Wiener(1.5)(blurred)
    assert err(deblur_in_linear_light(Wiener(1.5), blurred, guard=False)) < 0.97 * err(encoded) < err(blurred)
    seen = []

    def model(x):
        seen.append(x)
        return x * 0.9

    frames = [np.rint(blurred.permute(1, 2, 0).numpy() * 255).astype(np.uint8)] * 5
    list(ClipRestorer(temporal=4, deblur=model, linear_light=True, stabilise=False).restore(frames))
    assert all(float(s.max()) > 0.5 for s in seen)  # encoded values, not linear light (whose mean is far lower)
