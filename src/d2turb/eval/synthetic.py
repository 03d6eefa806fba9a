"""Synthetic evaluation (Table 1 protocol): PSNR / SSIM / LPIPS per turbulence bin and on average, for
several models side by side, on a dataset written by ``d2turb make-dataset``.

Outputs in ``out_dir``: ``results.json`` (per-bin means, per-sample values, notes), ``results.md``
(Markdown table laid out like the paper's Table 1), ``results.tex`` (the same in LaTeX) and
``grids/<bin>.png`` (labelled comparison grids: input | GT | each model).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import torch

from d2turb.data import PairDataset
from d2turb.data.layout import BIN_NAMES
from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX
from d2turb.errors import D2TurbError
from d2turb.eval.labels import GENERIC_STEMS, weights_label
from d2turb.eval.lpips import LPIPS
from d2turb.eval.metrics import KeyedMean, end_point_error, psnr, quantise_8bit, ssim
from d2turb.eval.report import comparison_grid, latex_table, markdown_table
from d2turb.io import write_image, write_json, write_text
from d2turb.restore import IdentityRestorer, Restorer
from d2turb.sim.params import BINS_RULE

logger = logging.getLogger(__name__)

ALL_METRICS = ("psnr", "ssim", "lpips", "epe", "psnr_tilt")
DEFAULT_METRICS = ("psnr", "ssim", "lpips")


def _unique_names(names: list[str]) -> list[str]:
    out = []
    for i, name in enumerate(names):
        out.append(name if names.count(name) == 1 else f"{name}#{names[: i + 1].count(name)}")
    return out


def _build_lpips(strict: bool, lpips_weights, lpips_backbone, lpips_net: str, device):
    """(LPIPS model or None, note). Missing LPIPS weights only raise when LPIPS was asked for explicitly."""
    try:
        return LPIPS(lpips_net, weights=lpips_weights, backbone=lpips_backbone).to(device), None
    except D2TurbError as exc:
        if strict:
            raise
        return None, f"LPIPS column omitted: {exc}"


def _lpips_or_note(metrics: list[str], strict: bool, lpips_weights, lpips_backbone, lpips_net: str, device):
    """(LPIPS model or None, notes); without its weights (and not ``strict``) "lpips" leaves ``metrics``."""
    model, note = _build_lpips(strict, lpips_weights, lpips_backbone, lpips_net, device)
    if not note:
        return model, []
    logger.warning("%s", note)
    metrics.remove("lpips")
    return None, [note]


def _indices(count: int, progress: bool):
    """range(count), with a tqdm bar when ``progress``."""
    if not progress:
        return range(count)
    from tqdm import tqdm

    return tqdm(range(count), desc="evaluate", unit="img")


def _lpips_requested(metrics, lpips_weights, lpips_backbone) -> bool:
    """LPIPS counts as asked for explicitly (missing weights → error) when its weights were pointed to
    (arguments or $D2TURB_LPIPS_WEIGHTS / $D2TURB_LPIPS_BACKBONE) or "lpips" was named in a metric list
    other than the default set; otherwise missing weights only drop the column, with a note."""
    pointed = (
        lpips_weights is not None
        or lpips_backbone is not None
        or any(os.environ.get(v) for v in ("D2TURB_LPIPS_WEIGHTS", "D2TURB_LPIPS_BACKBONE"))
    )
    named = metrics is not None and "lpips" in metrics and set(metrics) != set(DEFAULT_METRICS)
    return pointed or named


def _check_options(metrics: Sequence[str] | None, max_samples: int | None) -> list[str]:
    """The metric list (None: the default set); one-line errors for unknown metrics and max_samples < 1."""
    metrics = list(DEFAULT_METRICS if metrics is None else metrics)
    unknown = [m for m in metrics if m not in ALL_METRICS]
    if unknown or not metrics:
        raise D2TurbError(
            f"unknown metric {unknown[0]!r}; choose from {', '.join(ALL_METRICS)}" if unknown else "no metrics given"
        )
    if max_samples is not None and max_samples < 1:
        raise D2TurbError(f"max_samples must be >= 1, got {max_samples}")
    return metrics


def _scores(
    details: dict, item: dict, metrics: list[str], lpips_model, device
) -> tuple[dict[str, float], torch.Tensor]:
    """(metric → value, the 8-bit restored image) for one model's ``restore_with_details`` output on one sample."""
    pred, gt = quantise_8bit(details["restored"]), item["gt"]
    values = {}
    if "psnr" in metrics:
        values["psnr"] = float(psnr(pred, gt))
    if "ssim" in metrics:
        values["ssim"] = float(ssim(pred, gt))
    if "lpips" in metrics:
        with torch.no_grad():
            values["lpips"] = float(lpips_model(pred[None].to(device), gt[None].to(device))[0])
    if "epe" in metrics:  # both flows are backward flows: warp(tilt, flow) ≈ gt
        values["epe"] = float(end_point_error(details["bwd_flow_px"], item["bwd_flow_px"]))
    if "psnr_tilt" in metrics:
        values["psnr_tilt"] = float(psnr(quantise_8bit(details["deblurred"]), item["tilt"]))
    return values, pred


def _evaluate_sample(dataset, i: int, restorers: dict, metrics: list[str], lpips_model, device):
    """(record {id, bin, dr0, values: {model: {metric: value}}}, the item, each model's 8-bit output) of sample
    ``i``; a sample that cannot be read or restored raises D2TurbError."""
    try:
        item = dataset[i]
    except (OSError, ValueError, EOFError) as exc:  # a truncated .png / .npy of the dataset
        raise D2TurbError(f"cannot read ({exc.__class__.__name__}: {exc})") from exc
    bin_name = BIN_NAMES[int(item["bin"])] if 0 <= int(item["bin"]) < len(BIN_NAMES) else "unbinned"
    record = {"id": item["id"], "bin": bin_name, "dr0": round(float(item["dr0"]), 6), "values": {}}
    outputs = []
    for name, restorer in restorers.items():
        record["values"][name], pred = _scores(
            restorer.restore_with_details(item["turb"]), item, metrics, lpips_model, device
        )
        outputs.append(pred)
    return record, item, outputs


def _table(mean: KeyedMean, names: list[str], metrics: list[str]) -> dict:
    """table[model][metric][bin or "avg"]: the mean over the bin's samples (None without any), "avg" over all."""
    groups = {group: mean.compute(None if group == "avg" else group) for group in BIN_NAMES + ("avg",)}
    return {name: {m: {g: means.get((name, m)) for g, means in groups.items()} for m in metrics} for name in names}


def _write_grids(out: Path, grids: dict[str, list], col_labels: list[str]) -> dict[str, str]:
    """``grids/<bin>.png`` for each bin with rows; returns bin → path relative to ``out``."""
    grid_files = {}
    for bin_name, rows in grids.items():
        if rows:
            arr = comparison_grid([r[0] for r in rows], col_labels, [f"{bin_name}: {r[1]}" for r in rows])
            path = out / "grids" / f"{bin_name}.png"
            write_image(path, arr)
            grid_files[bin_name] = str(path.relative_to(out))
    return grid_files


def _write_reports(out: Path, results: dict, data_dir) -> None:
    """results.json, results.md (the Table 1 layout, notes, skipped samples, grids) and results.tex."""
    write_json(out / "results.json", results)
    counts, metrics, notes, skipped = results["bin_counts"], results["metrics"], results["notes"], results["skipped"]
    bins_line = ", ".join(f"{b}: {counts[b]}" for b in BIN_NAMES)
    md = [
        "# Synthetic evaluation\n",
        f"Dataset `{data_dir}` — {results['samples_evaluated']} samples ({bins_line}); "
        f"bins: D/r0 {BINS_RULE}. Avg = mean over all samples.\n",
        markdown_table(results["table"], metrics),
    ]
    md += [f"\n> **Note:** {n}\n" for n in notes]
    if skipped:
        md.append(f"\n## Skipped ({len(skipped)}, not in the means)\n")
        md += [f"- `{s['id']}`: {s['error']}" for s in skipped]
    if results["grids"]:
        md.append("\n" + "\n".join(f"![{b}]({p})" for b, p in results["grids"].items()) + "\n")
    write_text(out / "results.md", "\n".join(md))
    write_text(out / "results.tex", latex_table(results["table"], metrics))


def evaluate_synthetic(
    weights: Sequence,
    data_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    device: str = "cpu",
    metrics: Sequence[str] | None = None,
    max_samples: int | None = None,
    lpips_weights: str | os.PathLike | None = None,
    lpips_backbone: str | os.PathLike | None = None,
    lpips_net: str = "alex",
    tile: int = DEFAULT_TILE_PX,
    overlap: int = DEFAULT_OVERLAP_PX,
    grid_per_bin: int = 2,
    progress: bool = False,
    fail_fast: bool = False,
    on_skip=None,
) -> dict:
    """Evaluate models on a make-dataset folder; write results.json/.md/.tex and grids; return the results.

    ``weights``: .safetensors paths, weights names, "input" (identity baseline) or nn.Modules, in table order
    (put "ours" last). ``metrics``: None (or the default set psnr, ssim, lpips) drops LPIPS with a visible
    note if its local weights are missing; a non-default list naming "lpips", or LPIPS weights pointed to
    (``lpips_weights``/``lpips_backbone`` or $D2TURB_LPIPS_WEIGHTS/$D2TURB_LPIPS_BACKBONE) makes missing
    LPIPS weights an error. Per-bin values are means over the bin's samples; "avg" is the mean over all
    samples (not the mean of the three bin means). Restored images are quantised to 8 bits first.
    A sample whose files cannot be read (or whose restoration fails) is skipped: ``on_skip(message)`` is
    called and it is listed in ``results["skipped"]``; with ``fail_fast`` its error is raised instead.
    """
    if not weights:
        raise D2TurbError("evaluate: give at least one model (--weights PATH|NAME|input)")
    strict_lpips = _lpips_requested(metrics, lpips_weights, lpips_backbone)
    metrics = _check_options(metrics, max_samples)
    dataset = PairDataset(data_dir, skip_invalid=not fail_fast)
    count = len(dataset) if max_samples is None else min(len(dataset), max_samples)
    if count == 0:
        if dataset.invalid:
            raise D2TurbError(f"{data_dir}: no valid sample record ({dataset.invalid[0]})")
        raise D2TurbError(f"{data_dir}: the dataset has no samples")
    restorers = [Restorer(w, device=device, tile=tile, overlap=overlap) for w in weights]
    # a run folder's model.safetensors: its config's model name and folder, not "model"
    names = _unique_names(
        [weights_label(w) if Path(str(w)).stem.lower() in GENERIC_STEMS else r.name for w, r in zip(weights, restorers)]
    )
    lpips_model, notes = None, []
    if "lpips" in metrics:
        lpips_model, notes = _lpips_or_note(metrics, strict_lpips, lpips_weights, lpips_backbone, lpips_net, device)

    samples, skipped, grids, mean = [], [], {b: [] for b in BIN_NAMES}, KeyedMean(sync_on_compute=False)
    for message in dataset.invalid:  # meta lines that are not valid records: skipped like unreadable samples
        skipped.append({"id": message.split(": ", 1)[0].rsplit("/", 1)[-1], "error": message})
        if on_skip is not None:
            on_skip(message)
    # the identity baseline would repeat the input column
    grid_models = [i for i, r in enumerate(restorers) if not isinstance(r.model, IdentityRestorer)]
    for i in _indices(count, progress):
        try:
            record, item, outputs = _evaluate_sample(
                dataset, i, dict(zip(names, restorers)), metrics, lpips_model, device
            )
        except D2TurbError as exc:
            message = f"{Path(data_dir)} sample {dataset.records[i]['id']}: {exc}"
            if fail_fast:
                raise D2TurbError(message) from exc
            skipped.append({"id": dataset.records[i]["id"], "error": message})
            if on_skip is not None:
                on_skip(message)
            continue
        samples.append(record)
        mean.update({(n, m): v for n, values in record["values"].items() for m, v in values.items()}, record["bin"])
        if record["bin"] in grids and len(grids[record["bin"]]) < grid_per_bin:
            label = f"{item['id']}  D/r0={float(item['dr0']):.2f}"
            grids[record["bin"]].append(([item["turb"], item["gt"]] + [outputs[k] for k in grid_models], label))

    if not samples:
        raise D2TurbError(f"{data_dir}: none of the {count} samples could be evaluated")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = {
        "data": str(Path(data_dir)),
        "samples_evaluated": len(samples),
        "skipped": skipped,
        "bin_counts": {b: sum(s["bin"] == b for s in samples) for b in BIN_NAMES},
        "metrics": metrics,
        "models": names,
        "weights": [os.fspath(w) if isinstance(w, (str, os.PathLike)) else type(w).__name__ for w in weights],
        "table": _table(mean, names, metrics),
        "per_sample": samples,
        "notes": notes,
        "grids": _write_grids(out, grids, ["input", "GT"] + [names[k] for k in grid_models]),
        "protocol": "per-bin mean over samples; avg = mean over all samples; outputs quantised to 8 bits",
    }
    _write_reports(out, results, data_dir)
    return results
