"""Model cost: parameter counts (built on the meta device, no memory), FLOPs via FlopCounterMode, latency."""

from __future__ import annotations

import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from d2turb.models.registry import create_model


def count_parameters(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def parameter_count(name: str, **cfg) -> int:
    """Parameters of a registered model, built on the meta device (instant, no memory)."""
    with torch.device("meta"):
        return count_parameters(create_model(name, **cfg))


def flop_counts(model: torch.nn.Module, size: int | tuple[int, int] = 256, device="cpu") -> dict[str, int]:
    """FLOPs of one forward on a (1, 3, H, W) input, by operator (e.g. "aten.convolution", "aten.bmm") and "total".
    Multiply and add are counted separately (MACs = FLOPs / 2). FlopCounterMode counts convolutions and matmuls
    (including attention); elementwise ops (norms, activations, softmax, grid_sample) are not counted, as in the
    usual MAC counters. ``device="meta"`` with a model built on the meta device costs no compute."""
    h, w = (size, size) if isinstance(size, int) else size
    x = torch.zeros(1, 3, h, w, device=device)
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        model(x)
    counts = {str(op): int(n) for op, n in counter.get_flop_counts().get("Global", {}).items()}
    counts["total"] = int(counter.get_total_flops())
    return counts


def count_flops(model: torch.nn.Module, size: int | tuple[int, int] = 256, device="cpu") -> int:
    """Total FLOPs of one forward (see :func:`flop_counts`)."""
    return flop_counts(model, size, device)["total"]


def model_cost(name: str, size: int = 256, **cfg) -> dict:
    """Parameters, FLOPs and MACs of a registered model at size², computed on the meta device (no compute).
    ``conv_gmacs`` counts convolutions only: the convention of the Restormer and D²Turb papers' "GFLOPs"."""
    with torch.device("meta"):
        model = create_model(name, **cfg)
    counts = flop_counts(model, size, "meta")
    conv = counts.get("aten.convolution", 0)
    return {
        "params": count_parameters(model),
        "flops": counts["total"],
        "gmacs": counts["total"] / 2e9,
        "conv_gmacs": conv / 2e9,
        "size": size,
    }


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure_latency(
    model: torch.nn.Module,
    size: int | tuple[int, int] = 256,
    device="cpu",
    warmup: int = 1,
    repeats: int = 3,
    dtype=torch.float32,
) -> float:
    """Median wall time in seconds of one forward on a (1, 3, size, size) input."""
    device = torch.device(device)
    h, w = (size, size) if isinstance(size, int) else size
    model = model.to(device=device, dtype=dtype).eval()
    x = torch.rand(1, 3, h, w, device=device, dtype=dtype)
    times = []
    with torch.inference_mode():
        for i in range(warmup + repeats):
            _sync(device)
            t0 = time.perf_counter()
            model(x)
            _sync(device)
            if i >= warmup:
                times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def efficiency_entries() -> list[tuple[str, dict]]:
    """The efficiency table's rows: the paper's variants, then every other registered model at its default config."""
    from d2turb.models.registry import list_models

    entries = [("restormer", {}), ("nafnet", {})]
    entries += [("d2turb", {"backbone": "restormer", "injection": inj}) for inj in ("none", "concat", "aspi")]
    entries += [("d2turb", {"backbone": "nafnet", "injection": "aspi"}), ("d2turb_lite", {})]
    listed = {name for name, _ in entries}
    return entries + [(name, {}) for name in list_models() if name not in listed]


def benchmark(
    name: str,
    cfg: dict | None = None,
    size: int = 256,
    device="cpu",
    warmup: int = 1,
    repeats: int = 3,
    latency: bool = True,
    dtype=torch.float32,
) -> dict:
    """Parameters, FLOPs/MACs (meta device) and, unless ``latency=False``, the median forward latency on ``device``."""
    cfg = dict(cfg or {})
    result = {"model": name, "config": cfg, **model_cost(name, size, **cfg), "device": str(device)}
    if latency:
        torch.manual_seed(0)
        result["latency_s"] = measure_latency(create_model(name, **cfg), size, device, warmup, repeats, dtype)
        result.update(repeats=repeats, dtype=str(dtype).replace("torch.", ""))
    return result


def _label(result: dict) -> str:
    cfg = result["config"]
    return result["model"] + (f" ({', '.join(f'{k}={v}' for k, v in cfg.items())})" if cfg else "")


def markdown_table(results: list[dict]) -> str:
    """Efficiency table: model, params (M), GMACs (all / convolutions only), latency."""
    size = results[0]["size"] if results else 256
    lines = [
        f"| model | params (M) | GMACs @ {size}² | conv GMACs @ {size}² | latency (ms) | device |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r in results:
        lat = f"{r['latency_s'] * 1e3:.1f}" if "latency_s" in r else "–"
        lines.append(
            f"| {_label(r)} | {r['params'] / 1e6:.2f} | {r['gmacs']:.2f} | {r['conv_gmacs']:.2f} | {lat} "
            f"| {r['device']} |"
        )
    return "\n".join(lines) + "\n"
