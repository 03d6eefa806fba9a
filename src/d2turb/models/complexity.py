"""Model cost: parameter counts (built on the meta device, no memory), FLOPs via FlopCounterMode, latency."""

from __future__ import annotations

import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from d2turb.models.registry import create_model, list_models


def count_parameters(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def parameter_count(name: str, **cfg) -> int:
    """Parameters of a registered model, built on the meta device (instant, no memory)."""
    with torch.device("meta"):
        return count_parameters(create_model(name, **cfg))


def flop_counts(model: torch.nn.Module, size: int | tuple[int, int] = 256, device="cpu") -> dict[str, int]:
    """FLOPs of one inference forward (eval mode) on a (1, 3, H, W) input, by operator (e.g. "aten.convolution",
    "aten.bmm") and "total". Multiply and add are counted separately (MACs = FLOPs / 2). FlopCounterMode counts
    convolutions and matmuls (including attention); elementwise ops (norms, activations, softmax, grid_sample) and
    FFTs are not counted, as in the usual MAC counters. ``device="meta"`` with a model built on the meta device
    costs no compute."""
    h, w = (size, size) if isinstance(size, int) else size
    x = torch.zeros(1, 3, h, w, device=device)
    counter = FlopCounterMode(display=False)
    was_training = model.training
    model.eval()  # training-only branches (TurbNet's re-degradation) are not part of inference
    try:
        with torch.no_grad(), counter:
            model(x)
    finally:
        model.train(was_training)
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


# The D²Turb paper's efficiency table: (method, model, config, params in M, "GFLOPs" = convolution GMACs at 256²).
PAPER_EFFICIENCY: list[tuple[str, str, dict, float, float | None]] = [
    ("AT-Net", "atnet", {}, 3.05, None),
    ("TurbNet", "turbnet", {}, 26.57, None),
    ("TMT", "tmt", {}, 22.75, None),
    ("FocalNet", "focalnet", {}, 6.77, None),
    ("Restormer", "restormer", {}, 26.13, None),
    ("AdaIR", "adair", {}, 28.74, None),
    ("D²Turb+Restormer", "d2turb", {"backbone": "restormer", "injection": "aspi"}, 31.82, 150.51),
    ("D²Turb+FocalNet", "d2turb_focalnet", {}, 12.46, None),
    ("D²Turb+AdaIR", "d2turb_adair", {}, 34.43, None),
]
# Why a count differs from the paper's by more than 2 % (docs/models.md, "Baselines", has the details).
PAPER_NOTES = {
    "AT-Net": "both streams (MC-dropout prior + uncertainty-guided main stream), 3.49 M each; the paper's 3.05 M is "
    "within 1.2 % of the main stream alone as the released code's forward pass executes it (3.09 M)",
    "TMT": "single-frame TMT as a 2-D network; the published 3-D kernels' outer temporal taps, which only ever see "
    "zero padding with one frame, add 7.78 M: 22.75 M",
}
# Other rows of the project's own table: D²Turb ablations and the CPU-friendly NAFNet variants.
_PROJECT_ROWS: list[tuple[str, dict]] = [
    ("nafnet", {}),
    ("d2turb", {"backbone": "restormer", "injection": "none"}),
    ("d2turb", {"backbone": "restormer", "injection": "concat"}),
    ("d2turb", {"backbone": "nafnet", "injection": "aspi"}),
    ("d2turb_lite", {}),
]


def _paper_row(name: str, cfg: dict) -> tuple[str, str, dict, float, float | None] | None:
    return next((row for row in PAPER_EFFICIENCY if row[1] == name and row[2] == cfg), None)


def efficiency_entries() -> list[tuple[str, dict]]:
    """The efficiency table's rows: the paper's methods in its order, the project's ablation / CPU variants, then
    every other registered model at its default config."""
    entries = [(name, cfg) for _, name, cfg, _, _ in PAPER_EFFICIENCY] + _PROJECT_ROWS
    listed = {name for name, _ in entries}
    return entries + [(name, {}) for name in list_models() if name not in listed]


def latency_devices(device: str = "auto") -> list[str]:
    """ "auto" → ["cpu"] plus "cuda" when a GPU is present; "cpu" / "cuda" (or "cuda:N") → that device alone."""
    if device == "auto":
        return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    return [device]


def benchmark(
    name: str,
    cfg: dict | None = None,
    size: int = 256,
    device: str | list[str] = "cpu",
    warmup: int = 1,
    repeats: int = 3,
    latency: bool = True,
    dtype=torch.float32,
) -> dict:
    """Parameters, FLOPs/MACs (meta device) and, unless ``latency=False``, the median forward latency on each of
    ``device`` (a device or a list; ``latency_s`` = the first device's, ``latency`` = {device: seconds}). Rows of
    the paper's efficiency table also carry ``method``, ``paper_params`` (M) and ``paper_conv_gmacs``."""
    cfg = dict(cfg or {})
    devices = [device] if isinstance(device, (str, torch.device)) else list(device)
    result = {"model": name, "config": cfg, **model_cost(name, size, **cfg), "device": ", ".join(map(str, devices))}
    row = _paper_row(name, cfg)
    if row is not None:
        result.update(method=row[0], paper_params=row[3], paper_conv_gmacs=row[4])
    if latency:
        result["latency"] = {}
        for dev in devices:
            with torch.random.fork_rng(devices=[]):  # the same weights every run, the caller's RNG untouched
                torch.manual_seed(0)
                model = create_model(name, **cfg)
            result["latency"][str(dev)] = measure_latency(model, size, dev, warmup, repeats, dtype)
        result["latency_s"] = result["latency"][str(devices[0])]
        result.update(repeats=repeats, dtype=str(dtype).replace("torch.", ""))
    return result


def _label(result: dict) -> str:
    cfg = result["config"]
    return result["model"] + (f" ({', '.join(f'{k}={v}' for k, v in cfg.items())})" if cfg else "")


def _ms(result: dict, kind: str) -> str:
    seconds = [s for dev, s in result.get("latency", {}).items() if dev.split(":")[0] == kind]
    return f"{seconds[0] * 1e3:.1f}" if seconds else "–"


def markdown_table(results: list[dict]) -> str:
    """Efficiency table: method, model, params (ours | paper | difference), GMACs (all | convolutions only | paper's
    "GFLOPs", which are convolution MACs), CPU and CUDA latency; notes under the table for differences over 2 %."""
    size = results[0]["size"] if results else 256
    lines = [
        f"| method | model | params (M) | paper (M) | Δ | GMACs @ {size}² | conv GMACs @ {size}² | paper GMACs "
        "| CPU latency (ms) | CUDA latency (ms) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    notes = []
    for r in results:
        paper = r.get("paper_params")
        delta = f"{(r['params'] / 1e6 - paper) / paper:+.1%}" if paper else "–"
        method = r.get("method", "–")
        if method in PAPER_NOTES and paper and abs(r["params"] / 1e6 - paper) / paper > 0.02:
            notes.append(f"{method}: {PAPER_NOTES[method]}.")
            method += f" [{len(notes)}]"
        paper_text = f"{paper:.2f}" if paper else "–"
        paper_macs = f"{r['paper_conv_gmacs']:.2f}" if r.get("paper_conv_gmacs") else "–"
        lines.append(
            f"| {method} | {_label(r)} | {r['params'] / 1e6:.2f} | {paper_text} | {delta} | {r['gmacs']:.2f} "
            f"| {r['conv_gmacs']:.2f} | {paper_macs} | {_ms(r, 'cpu')} | {_ms(r, 'cuda')} |"
        )
    text = "\n".join(lines) + "\n"
    if notes:
        text += "\n" + "\n".join(f"[{i}] {n}" for i, n in enumerate(notes, 1)) + "\n"
    return text
