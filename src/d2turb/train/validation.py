"""Validation during training: the validation set (this rank's share of ``val.pairs``, or pairs synthesised once
from a pack's val images) and the mean metrics of a model on it over all ranks, overall and per turbulence bin."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable

import torch
from torch.utils.data import DataLoader, Subset

from d2turb.data import PairDataset, crop_sample
from d2turb.data.layout import BIN_NAMES
from d2turb.data.pack_read import PackCrops
from d2turb.eval.metrics import KeyedMean, end_point_error, psnr, ssim
from d2turb.train.config import Config

METRICS = ("psnr", "ssim", "psnr_input", "ssim_input", "epe", "epe_zero")
_VAL_IMAGE_SEED_STRIDE = 1009  # seed step between a pack's val images; the bin's index adds 0, 1, 2: a seed per pair


class Validation:
    """The validation set of a run (this rank's share; :attr:`batches` is None without one) and its metrics.

    Args:
        cfg: the run's config (``val``; ``data.patch`` and ``data.on_the_fly`` for a pack).
        rank: this process's rank.
        world: the number of processes.
        device: the training device (a pack's pairs are synthesised and kept there).
        make_synthesis: ``(bins, seed) -> OnTheFlySynthesis`` on ``device``.
    """

    def __init__(self, cfg: Config, rank: int, world: int, device: torch.device, make_synthesis: Callable) -> None:
        self.cfg, self.rank, self.world, self.device, self.make_synthesis = cfg, rank, world, device, make_synthesis
        val = cfg.val
        self.crop = val.crop if val.pairs is not None else None  # pack pairs are synthesised at the crop size
        self.batches: Iterable[dict] | None = None
        if val.pairs is not None:
            dataset = PairDataset(val.pairs)
            n = len(dataset) if val.max_images is None else min(len(dataset), val.max_images)
            shard = Subset(dataset, list(range(rank, n, world)))
            self.batches = DataLoader(shard, batch_size=val.batch, shuffle=False, num_workers=0)
        elif val.pack is not None:
            self.batches = self.pack_batches()

    def pack_batches(self) -> list[dict]:
        """One centre crop per val image × one pair per bin, each from its own seed (so the set does not depend
        on the number of processes); this rank's share, batched by ``val.batch``."""
        val, otf = self.cfg.val, self.cfg.data.on_the_fly
        size = val.crop or self.cfg.data.patch
        crops = PackCrops(val.pack, patch=size, split="val", depth=otf.depth, device=self.device).center_crops(size)
        if val.max_images is not None:
            crops = crops[: val.max_images]
        pairs = []
        for k, crop in enumerate(crops):
            for j, b in enumerate(otf.bins):
                if (k * len(otf.bins) + j) % self.world != self.rank:
                    continue
                synth = self.make_synthesis([b], seed=val.seed + _VAL_IMAGE_SEED_STRIDE * k + j)
                batch = {"gt": crop["gt"][None], "depth": crop["depth"][None], "id": [crop["id"]]}
                out = synth(batch)
                pairs.append({key: out[key] for key in ("turb", "gt", "bwd_flow_px", "bin")})
        return [
            {key: torch.cat([p[key] for p in pairs[i : i + val.batch]]) for key in pairs[0]}
            for i in range(0, len(pairs), val.batch)
        ]

    @torch.no_grad()
    def metrics(
        self,
        model: torch.nn.Module,
        prepare: Callable[[torch.Tensor], torch.Tensor],
        autocast: Callable[[], contextlib.AbstractContextManager],
    ) -> dict[str, float]:
        """Mean metrics of ``model`` (in eval mode meanwhile) over the validation set of all ranks (a collective
        under DDP: every rank calls it).

        Args:
            model: ``turb (B, 3, H, W) -> {"restored", "bwd_flow_px" (or None)}``.
            prepare: the model's input from a batch's ``turb`` (device, memory format).
            autocast: the training's autocast context (bf16 or none).

        Returns:
            ``psnr``, ``ssim`` of ``restored`` (clamped to [0, 1]) and of the input (``psnr_input``,
            ``ssim_input``), the flow end-point error ``epe`` (px, mean over pixels of ‖V̂ − V‖₂) and that of zero
            flow ``epe_zero`` (mean ‖V‖₂); the same per bin as ``<metric>_<bin>``. Means without samples are
            left out.
        """
        was_training = model.training
        model.eval()
        mean = KeyedMean(sync_on_compute=self.world > 1)
        try:
            for batch in self.batches:
                if self.crop:
                    h, w = batch["gt"].shape[-2:]
                    size = min(self.crop, h, w)
                    batch = crop_sample(batch, (h - size) // 2, (w - size) // 2, size)  # deterministic centre crop
                with autocast():
                    out = model(prepare(batch["turb"]))
                mean.update(self._values(out, batch), groups=batch.get("bin"))
        finally:
            model.train(was_training)
        overall = mean.compute()
        per_bin = {name: mean.compute(i) for i, name in enumerate(BIN_NAMES)}
        means = {k: overall[k] for k in METRICS if k in overall}
        means |= {f"{k}_{name}": per_bin[name][k] for k in METRICS for name in BIN_NAMES if k in per_bin[name]}
        return {k: v for k, v in means.items() if not math.isnan(v)}

    def _values(self, out: dict, batch: dict) -> dict[str, torch.Tensor]:
        """Per-pair metric values (B,) of one batch."""
        gt, turb = batch["gt"].to(self.device).float(), batch["turb"].to(self.device).float()
        restored = out["restored"].float().clamp(0, 1)
        values = {"psnr": psnr(restored, gt), "ssim": ssim(restored, gt)}
        values |= {"psnr_input": psnr(turb, gt), "ssim_input": ssim(turb, gt)}
        flow = batch.get("bwd_flow_px")
        if out.get("bwd_flow_px") is not None and flow is not None:
            flow = flow.to(self.device).float()
            values |= {"epe": end_point_error(out["bwd_flow_px"].float(), flow), "epe_zero": end_point_error(flow)}
        return values
