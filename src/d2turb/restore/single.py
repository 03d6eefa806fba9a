"""Restore images of any size with a trained D²Turb model: tiled inference with seamless blending.

Tiling (see docs/restore.md): the image is cut into overlapping tiles; every tile runs through the
model; its *deblurred* image (Î_tilt) and *flow* (V̂) are accumulated with a smooth window that is > 0
everywhere and then divided by the accumulated weight. The geometric rectification of Eq. 9,
Î_clean = S(Î_tilt, V̂), is then applied ONCE to the whole blended image (in row strips to bound
memory) rather than per tile: the backward flow near a tile border points outside the tile, and a
per-tile warp would sample the tile's clamped border instead of the true neighbouring pixels. A global
warp of blended, seamless fields cannot create a seam, and it equals the untiled model's warp
wherever the tiles agree with the untiled model.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import torch
from torch import nn

from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX
from d2turb.deprecation import AliasDict
from d2turb.device import resolve_device
from d2turb.errors import D2TurbError
from d2turb.io import read_image
from d2turb.models.common import pad_to_multiple
from d2turb.models.hub import IDENTITY_NAME, recommended_weights, resolve_weights
from d2turb.models.output import ModelOutput, model_output
from d2turb.models.weights import load_pretrained
from d2turb.ops.checks import check_image_tensor
from d2turb.ops.warp import base_grid, sample_at

_WARP_STRIP_PIXELS = 1 << 21  # output pixels per strip of the global warp (bounds its temporaries)
_WINDOW_FLOOR = 1e-6  # tile windows never reach 0, so every pixel has a positive accumulated weight


class RestoreDetails(AliasDict):
    """What :meth:`Restorer.restore_with_details` returns: restored, deblurred, bwd_flow_px (``flow``: deprecated)."""

    aliases = {"flow": "bwd_flow_px"}
    what = "restore_with_details()"


class IdentityRestorer(nn.Module):
    """The "input" baseline: returns its input unchanged (zero flow)."""

    def forward(self, x: torch.Tensor) -> ModelOutput:
        return model_output(x, x, torch.zeros_like(x[:, :2]))


def load_restoration_model(weights, device: str | torch.device = "cpu") -> tuple[nn.Module, str]:
    """(model in eval mode on ``device``, display name) from a path, a name, "input" or an nn.Module."""
    if isinstance(weights, nn.Module):
        return weights.to(device).eval(), type(weights).__name__
    resolved = resolve_weights(weights)
    if resolved == IDENTITY_NAME:
        return IdentityRestorer().to(device), IDENTITY_NAME

    model = load_pretrained(str(resolved), device=str(device))
    return model.to(device).eval(), Path(resolved).stem


def tile_starts(length: int, tile: int, overlap: int) -> list[int]:
    """Start offsets of tiles of size ``tile`` covering [0, length) with at least ``overlap`` shared pixels."""
    if length <= tile:
        return [0]
    stride = tile - overlap
    count = math.ceil((length - tile) / stride) + 1
    starts = [min(i * stride, length - tile) for i in range(count)]
    return sorted(set(starts))


def axis_window(size: int, overlap: int, taper_start: bool, taper_end: bool) -> torch.Tensor:
    """1-D tile weight along one axis. On a tapered side (one that has a neighbouring tile) the first
    ``overlap // 4`` pixels — the ones whose receptive field is cut by the tile edge — get the floor
    weight, then a raised cosine rises to 1 over the next ``overlap // 2`` pixels (max slope π/overlap).
    Two tiles sharing ``overlap`` pixels have complementary weights (sum 1); the floor keeps the window
    > 0 everywhere, so the accumulated weight never vanishes."""
    w = torch.ones(size, dtype=torch.float64)
    overlap = min(overlap, size // 2)
    guard = overlap // 4
    ramp = overlap - 2 * guard
    if ramp > 0:
        t = (torch.arange(ramp, dtype=torch.float64) + 0.5) / ramp
        rise = torch.cat([torch.zeros(guard, dtype=torch.float64), torch.sin(0.5 * math.pi * t) ** 2])
        if taper_start:
            w[: guard + ramp] = rise
        if taper_end:
            w[size - guard - ramp :] = torch.minimum(w[size - guard - ramp :], rise.flip(0))
    return w.clamp_min(_WINDOW_FLOOR).float()


def warp_in_strips(image: torch.Tensor, flow: torch.Tensor, pad_to: int = 1) -> torch.Tensor:
    """``d2turb.ops.warp(image, flow)`` (border padding, align_corners=True) computed in row strips so
    the sampling grid of a 12-megapixel image never exists at once. Same result as the one-shot warp.

    ``pad_to`` > 1: the warp samples the image padded at the bottom/right to a multiple of ``pad_to`` (reflect,
    replicate where the pad is not smaller than the side: as D²Turb pads its input), and the result is cropped
    back, as the authors' model warps its padded canvas: a flow that points up to the pad past the bottom/right
    edge then sees mirrored content, not the clamped edge."""
    _, _, h, w = image.shape
    canvas = pad_to_multiple(image, pad_to)[0] if pad_to > 1 else image
    out = torch.empty_like(image)
    rows = max(1, _WARP_STRIP_PIXELS // max(w, 1))
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        grid = base_grid(r1 - r0, w, flow.device, flow.dtype)
        grid[:, 1] += r0  # absolute rows, exact in floating point
        out[:, :, r0:r1] = sample_at(canvas, grid + flow[:, :, r0:r1])
    return out


class Restorer:
    """Restore turbulence-degraded images of any size.

    ``weights``: a .safetensors path from ``save_pretrained``, a weights name (see
    :func:`weights_search_path`), ``"input"`` (identity baseline), an ``nn.Module`` returning the model
    output dict (deblurred, restored, flow), or None: the recommended shipped model
    (:func:`d2turb.models.hub.recommended_weights`, named in one line on stderr; D2TurbError if none is
    shipped). ``device``: see :func:`d2turb.device.resolve_device`. Images
    larger than ``tile`` are processed in overlapping tiles (``overlap`` pixels shared) and blended
    seamlessly; CUDA runs under bf16 autocast. A model output with NaN/inf raises ``D2TurbError``.

    Args:
        weights: see above (a path, a name, ``"input"``, a module, or None for the recommended shipped model).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``.
        tile: largest side processed at once (px, >= 16); larger images go in tiles.
        overlap: pixels shared by neighbouring tiles (0 to tile/2).
        progress: show a progress bar over the tiles.

    Example:
        >>> restorer = Restorer("input")  # the identity baseline: no weights needed
        >>> restorer.restore(torch.rand(3, 40, 56)).shape
        torch.Size([3, 40, 56])
    """

    def __init__(
        self,
        weights=None,
        device: str = "cpu",
        tile: int = DEFAULT_TILE_PX,
        overlap: int = DEFAULT_OVERLAP_PX,
        progress: bool = False,
    ):
        if not isinstance(tile, int) or tile < 16:
            raise D2TurbError(f"tile size must be an integer >= 16, got {tile}")
        if not isinstance(overlap, int) or overlap < 0 or overlap > tile // 2:
            raise D2TurbError(f"overlap must be between 0 and tile/2 = {tile // 2}, got {overlap}")
        self.device = resolve_device(device)
        self.tile, self.overlap, self.progress = tile, overlap, progress
        if weights is None:
            weights = recommended_weights()
            print(f"restoring with the shipped model {weights.stem} (MODEL_CARD.md)", file=sys.stderr)
        self.model, self.name = load_restoration_model(weights, self.device)

    # -- public API -------------------------------------------------------------------------------
    def restore(self, image) -> torch.Tensor:
        """The restored image.

        Args:
            image: float in [0, 1] (or an image file's path).

        Returns:
            The restored image, float32 in [0, 1], on the CPU.

        Shape:
            - image: :math:`(3, H, W)` or :math:`(B, 3, H, W)`.
            - Output: the input's shape.
        """
        return self.restore_with_details(image)["restored"]

    def restore_with_details(self, image) -> dict:
        """dict(restored, deblurred, bwd_flow_px): images shaped like the input, and the model's backward flow V̂
        (…, 2, H, W) in pixels, x then y, ``warp(deblurred, bwd_flow_px) ≈ restored`` (zero for a model without a
        rectifier); ``flow``, its deprecated name, still reads it with a ``DeprecationWarning`` (once)."""
        x, single = self._as_batch(image)
        with torch.no_grad():
            outs = [self._restore_one(x[i : i + 1]) for i in range(x.shape[0])]
        result = {k: torch.cat([o[k] for o in outs]) for k in ("restored", "deblurred", "bwd_flow_px")}
        return RestoreDetails({k: v[0] for k, v in result.items()} if single else result)

    # -- internals --------------------------------------------------------------------------------
    @staticmethod
    def _as_batch(image) -> tuple[torch.Tensor, bool]:
        if isinstance(image, (str, os.PathLike)):
            image = read_image(image)
        if not isinstance(image, torch.Tensor):
            raise D2TurbError(f"restore: expected a tensor or an image path, got {type(image).__name__}")
        single = image.ndim == 3
        x = image[None] if single else image
        check_image_tensor(x, "restore input", channels=3)
        if x.shape[-1] < 2 or x.shape[-2] < 2:
            raise D2TurbError(f"restore input: image is too small ({x.shape[-1]}x{x.shape[-2]})")
        return x.float().clamp(0, 1), single

    def _run_model(self, x: torch.Tensor, keep_restored: bool = False) -> dict:
        x = x.to(self.device)
        with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.device.type == "cuda"):
            out = self.model(x)
        if not isinstance(out, dict) or ("restored" not in out and "deblurred" not in out):
            raise D2TurbError(f"model {self.name} did not return a dict with 'restored'/'deblurred'")
        deblurred = out.get("deblurred", out.get("restored"))
        # a model of another package may name it "flow" only
        flow = out["bwd_flow_px"] if "bwd_flow_px" in out else out.get("flow")
        if not all(torch.isfinite(v).all() for v in (deblurred, flow, out.get("restored")) if v is not None):
            raise D2TurbError(
                f"model {self.name} produced NaN or infinite values; refusing to write them (corrupt weights?)"
            )
        result = {"deblurred": deblurred.float().cpu()}
        if flow is not None:
            result["bwd_flow_px"] = flow.float().cpu()
        if flow is None or keep_restored:  # a model without a rectifier: its restored output is blended as is
            result["restored"] = out.get("restored", deblurred).float().cpu()
        return result

    def _restore_one(self, x: torch.Tensor) -> dict:
        """x (1,3,H,W) on CPU → dict of (1,·,H,W) CPU tensors."""
        _, _, h, w = x.shape
        ys, xs = tile_starts(h, self.tile, self.overlap), tile_starts(w, self.tile, self.overlap)
        boxes = [(y0, x0, min(self.tile, h), min(self.tile, w)) for y0 in ys for x0 in xs]
        acc: dict[str, torch.Tensor] = {}
        weight = torch.zeros(1, 1, h, w)
        bar = None
        if self.progress and len(boxes) > 1:
            from tqdm import tqdm

            bar = tqdm(total=len(boxes), desc="tiles", unit="tile", leave=False)
        single = len(boxes) == 1
        for y0, x0, th, tw in boxes:
            out = self._run_model(x[:, :, y0 : y0 + th, x0 : x0 + tw], keep_restored=single)
            win = (
                axis_window(th, self.overlap, y0 > 0, y0 + th < h)[:, None]
                * axis_window(tw, self.overlap, x0 > 0, x0 + tw < w)[None, :]
            )
            for key, value in out.items():
                if value.shape[-2:] != (th, tw):
                    raise D2TurbError(
                        f"model {self.name} returned {key} of size {tuple(value.shape[-2:])} for a {th}x{tw} tile"
                    )
                if key not in acc:
                    acc[key] = torch.zeros(1, value.shape[1], h, w)
                acc[key][:, :, y0 : y0 + th, x0 : x0 + tw].addcmul_(value, win)
            weight[:, :, y0 : y0 + th, x0 : x0 + tw] += win
            if bar is not None:
                bar.update()
        if bar is not None:
            bar.close()
        for value in acc.values():
            value.div_(weight)
        deblurred = acc["deblurred"]
        if "bwd_flow_px" in acc and single and "restored" in acc:  # one tile: the model's Eq. 9, on its padded canvas
            flow, restored = acc["bwd_flow_px"], acc["restored"]
        elif "bwd_flow_px" in acc:
            flow = acc["bwd_flow_px"]
            if flow.any():  # Eq. 9, on the whole blended image (on the model's device), on the model's canvas
                pad_to = int(getattr(self.model, "multiple", 1) or 1)
                restored = warp_in_strips(deblurred.to(self.device), flow.to(self.device), pad_to).cpu()
            else:
                restored = deblurred.clone()
        else:
            flow, restored = torch.zeros(1, 2, h, w), acc["restored"]
        return {"restored": restored.clamp_(0, 1), "deblurred": deblurred.clamp_(0, 1), "bwd_flow_px": flow}
