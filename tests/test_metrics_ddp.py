"""Metric accumulators under torch.distributed: 2 gloo processes on CPU give the single-process result (PSNR, SSIM,
and KeyedMean with keys and groups that differ between the ranks).

Kept apart from the other metric tests so the spawned workers import only torch and d2turb.
"""

import json

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from d2turb.eval.metrics import PSNR, SSIM, KeyedMean, psnr, ssim


def _pairs(n=5, h=48, w=40, seed=0):
    """n (pred, target) pairs in [0, 1] with different noise levels."""
    g = torch.Generator().manual_seed(seed)
    target = torch.nn.functional.avg_pool2d(torch.rand(n, 3, h, w, generator=g), 3, 1, 1)  # some structure
    noise = torch.randn(n, 3, h, w, generator=g) * torch.linspace(0.02, 0.3, n).view(n, 1, 1, 1)
    return (target + noise).clamp(0, 1), target


def _binned_values():
    """Per-sample values and bins: with two ranks taking every other sample, only rank 0 gets the "strong" ones."""
    g = torch.Generator().manual_seed(1)
    bins = ["weak", "medium", "strong", "weak", "medium", "weak", "strong"]
    return {"psnr": 30 + 5 * torch.randn(len(bins), generator=g), "epe": torch.rand(len(bins), generator=g)}, bins


def _ddp_worker(rank, world_size, init_file, out_file):
    torch.set_num_threads(1)
    torch.distributed.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size)
    pred, target = _pairs()
    metrics = {"psnr": PSNR(), "ssim": SSIM(), "ssim_uniform": SSIM(gaussian=False)}
    for i in range(rank, len(pred), world_size):  # rank 0: images 0, 2, 4; rank 1: 1, 3 (unequal shares)
        for m in metrics.values():
            m.update(pred[i : i + 1], target[i : i + 1])
    result = {k: m.compute() for k, m in metrics.items()}
    keyed = KeyedMean()  # per-bin values of _binned_values(); rank 1 never sees the "strong" bin nor the key "epe"
    values, bins = _binned_values()
    for i in range(rank, len(bins), world_size):
        batch = {"psnr": values["psnr"][i : i + 1]} | ({"epe": values["epe"][i : i + 1]} if rank == 0 else {})
        keyed.update(batch, groups=[bins[i]])
    result["keyed"] = {str(g): keyed.compute(g) for g in (None, "weak", "medium", "strong")}
    result["keyed_count_strong"] = keyed.count("psnr", "strong")
    with open(f"{out_file}.{rank}", "w") as f:
        json.dump(result, f)
    torch.distributed.destroy_process_group()


@pytest.mark.slow
def test_ddp_all_reduce_equals_single_process(tmp_path):
    out = tmp_path / "result"
    mp.spawn(_ddp_worker, args=(2, str(tmp_path / "init"), str(out)), nprocs=2, join=True)
    pred, target = _pairs()
    expected = {
        "psnr": psnr(pred, target).mean().item(),
        "ssim": ssim(pred, target).mean().item(),
        "ssim_uniform": ssim(pred, target, gaussian=False).mean().item(),
    }
    values, bins = _binned_values()  # numpy oracle: means over the samples of each bin; "epe" only from rank 0's
    psnr_v, epe_v, bins = values["psnr"].double().numpy(), values["epe"].double().numpy(), np.array(bins)
    rank0 = np.arange(len(bins)) % 2 == 0
    keyed = {"None": {"psnr": psnr_v.mean(), "epe": epe_v[rank0].mean()}}
    for b in ("weak", "medium", "strong"):
        keyed[b] = {"psnr": psnr_v[bins == b].mean(), "epe": epe_v[rank0 & (bins == b)].mean()}
    for rank in range(2):
        got = json.loads((tmp_path / f"result.{rank}").read_text())
        for k, v in expected.items():
            assert got[k] == pytest.approx(v, abs=1e-9), (rank, k)
        assert got["keyed"].keys() == keyed.keys()
        for group, means in keyed.items():  # the same keys, groups and means on each rank
            assert got["keyed"][group] == pytest.approx(means, rel=1e-12), (rank, group)
        assert got["keyed_count_strong"] == 2
