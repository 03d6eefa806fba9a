"""No-reference evaluation of real turbulence images (no ground truth), paper Table 2.

``evaluate_real`` scores every image of a folder (with ``recursive``, of its sub-folders too: one clip per
folder, means per folder) with NIQE / PIQE, optionally after restoring it with each model in ``weights``
("input" = the unrestored image), and writes ``results.json``, ``results.md`` and, with models, comparison
grids ``grids/<name>.png`` (input | model 1 | ...).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from d2turb.errors import D2TurbError
from d2turb.eval.labels import weights_label
from d2turb.eval.metrics import KeyedMean
from d2turb.eval.musiq import MUSIQ
from d2turb.eval.niqe import niqe
from d2turb.eval.piqe import piqe
from d2turb.io import check_unique_stems, list_images, read_image, write_image, write_json, write_text
from d2turb.restore import Restorer
from d2turb.video import VIDEO_SUFFIXES

IDENTITY = "input"
NO_REFERENCE = ("niqe", "piqe", "musiq")
HIGHER_IS_BETTER = ("musiq",)
FULL_REFERENCE = ("psnr", "ssim", "lpips")


def no_reference_metric(
    name: str, device: str = "cpu", musiq_weights: str | None = None
) -> Callable[[torch.Tensor], float]:
    """(3, H, W) image in [0, 1] → float, for "niqe", "piqe" (lower is better) or "musiq" (higher is better)."""
    if name == "niqe":
        return lambda img: float(niqe(img))
    if name == "piqe":
        return lambda img: float(piqe(img))
    if name == "musiq":  # weights: the argument, $D2TURB_MUSIQ_WEIGHTS or the cache folder (d2turb.eval.musiq)
        model = MUSIQ(weights=musiq_weights, device=device)
        return lambda img: float(model(img)[0])
    if name in FULL_REFERENCE:
        raise D2TurbError(f"{name} needs ground truth; real images have none (use --data DATASET_DIR for {name})")
    raise D2TurbError(f"unknown metric {name!r} for real images; available: {', '.join(NO_REFERENCE)}")


def parse_metrics(text: str | list[str]) -> list[str]:
    names = text.split(",") if isinstance(text, str) else list(text)
    names = [n.strip().lower() for n in names if n.strip()]
    if not names:
        raise D2TurbError("no metrics given (e.g. --metrics niqe,piqe)")
    return list(dict.fromkeys(names))


def _model_names(weights: list[str]) -> list[str]:
    labels = [weights_label(w) for w in weights]  # run folders' model.safetensors: config name (folder)
    return [str(w) if labels.count(s) > 1 else s for w, s in zip(weights, labels)]


def _videos(folder: Path, recursive: bool) -> list[Path]:
    """Video files in ``folder`` (with ``recursive``, in its sub-folders too), hidden ones left out, sorted."""
    try:
        entries = list(folder.rglob("*") if recursive else folder.iterdir())
    except OSError:
        return []  # list_images has reported the folder
    found = [
        p
        for p in entries
        if p.suffix.lower() in VIDEO_SUFFIXES
        and not any(part.startswith(".") for part in p.relative_to(folder).parts)
        and p.is_file()
    ]
    return sorted(found, key=lambda p: p.relative_to(folder).parts)


def _default_restorer(weights: str, device: str):
    return Restorer(weights, device=device).restore


GRID_LABEL_H = 16  # rows of the label strip above the images of a grid


def _grid(images: list[torch.Tensor], labels: list[str] | None = None, gap: int = 4) -> torch.Tensor:
    """Input | each model's output side by side at full resolution (real frames are inspected pixel by pixel;
    :func:`d2turb.eval.report.comparison_grid` fits synthetic samples into labelled cells instead), under a
    white strip of :data:`GRID_LABEL_H` rows naming each column (``labels``)."""
    h = max(im.shape[1] for im in images)
    padded = [torch.nn.functional.pad(im, (0, 0, 0, h - im.shape[1]), value=1.0) for im in images]
    sep = torch.ones(3, h, gap)
    parts = [p for im in padded for p in (im, sep)][:-1]
    grid = torch.cat(parts, dim=2)
    if not labels:
        return grid
    strip = Image.new("RGB", (grid.shape[2], GRID_LABEL_H), (255, 255, 255))
    draw, font, left = ImageDraw.Draw(strip), ImageFont.load_default(), 0
    for im, text in zip(images, labels):
        draw.text((left + 2, 2), text, fill=(0, 0, 0), font=font)
        left += im.shape[2] + gap
    strip = torch.from_numpy(np.asarray(strip).copy()).permute(2, 0, 1).float() / 255
    return torch.cat([strip, grid], dim=1)


def _fmt(v: float) -> str:
    return "nan" if math.isnan(v) else f"{v:.4f}"


def _markdown(results: dict) -> str:
    metrics, models = results["metrics"], list(results["models"])
    lines = [
        f"# No-reference evaluation of `{results['data']}` ({len(results['images'])} images)",
        "",
        "Lower is better for NIQE and PIQE, higher for MUSIQ. These are no-reference scores: they compare image "
        "statistics with clean photographs, not with the scene, so a better score is a hint to look at the grids, "
        "not proof of restoration (a broken model can score better than its input; docs/metrics.md).",
        "",
        "| model | " + " | ".join(f"{m.upper()} {'↑' if m in HIGHER_IS_BETTER else '↓'}" for m in metrics) + " |",
        "|---|" + "---:|" * len(metrics),
    ]
    for model in models:
        lines.append(f"| {model} | " + " | ".join(_fmt(results["models"][model][m]["mean"]) for m in metrics) + " |")
    if "folders" in results:
        lines += [
            "",
            "## Means per folder",
            "",
            "| folder | images | model | " + " | ".join(m.upper() for m in metrics) + " |",
            "|---|---:|---|" + "---:|" * len(metrics),
        ]
        for folder, entry in results["folders"].items():
            for model in models:
                means = " | ".join(_fmt(entry["models"][model][m]) for m in metrics)
                lines.append(f"| {folder} | {len(entry['images'])} | {model} | {means} |")
    for m in metrics:
        lines += [
            "",
            f"## {m.upper()} per image",
            "",
            "| image | " + " | ".join(models) + " |",
            "|---|" + "---:|" * len(models),
        ]
        for name in results["images"]:
            lines.append(
                f"| {name} | " + " | ".join(_fmt(results["models"][k][m]["per_image"][name]) for k in models) + " |"
            )
    if results.get("skipped"):
        lines += ["", "## Skipped (not in the means)", ""]
        lines += [f"- `{s['file']}`: {s['error']}" for s in results["skipped"]]
    if results.get("not_scored"):
        lines += ["", "## Not scored (videos)", ""]
        lines += [f"- `{s['file']}`: {s['reason']}" for s in results["not_scored"]]
    return "\n".join(lines) + "\n"


VIDEO_NOT_SCORED = (
    "a video: --real scores image files; `d2turb restore VIDEO --weights input --out DIR` writes its frames as PNGs "
    "(and DIR/VIDEO.mp4), then `d2turb evaluate --real DIR` scores them"
)


def _inputs(real_dir: Path, recursive: bool, max_samples: int | None) -> tuple[list[Path], list[dict]]:
    """(the images to score, [{"file", "reason"} of each video found beside them]); raises ``D2TurbError`` when
    there is no image (naming the sub-folders' images without ``recursive``, and the videos)."""
    paths = list_images(real_dir, recursive=recursive)
    if max_samples is not None:
        paths = paths[:max_samples]
    videos = _videos(real_dir, recursive)
    not_scored = [{"file": v.relative_to(real_dir).as_posix(), "reason": VIDEO_NOT_SCORED} for v in videos]
    if not paths:
        nested = not recursive and list_images(real_dir, recursive=True)
        raise D2TurbError(
            f"{real_dir}: no images found"
            + (" (its sub-folders hold some: --recursive)" if nested else "")
            + (f" ({len(videos)} video file(s), not scored: {not_scored[0]['reason']})" if videos else "")
        )
    return paths, not_scored


def _restore_and_score(path: Path, restorers: dict, scorers: dict) -> tuple[torch.Tensor, dict, dict]:
    """(the image at ``path``, {model: its output}, {(model, metric): score}); a failing score raises
    ``D2TurbError`` naming the file, the model and the metric."""
    image = read_image(path)
    outputs = {}
    for n, r in restorers.items():
        outputs[n] = image if r is None else r(image).detach().float().cpu().clamp(0, 1)
    scores = {}
    for n, restored in outputs.items():
        for m, score in scorers.items():
            try:
                scores[n, m] = score(restored)
            except D2TurbError as exc:
                raise D2TurbError(f"{path} ({n}, {m}): {exc}") from exc
    return image, outputs, scores


def _folder_means(names: list[str], mean: KeyedMean, metric_names: list[str], model_names: list[str]) -> dict:
    """``results["folders"]``: per folder of the scored ``names`` {"images", "models": {model: {metric: mean}}}."""
    folders: dict[str, list[str]] = {}
    for name in names:
        folders.setdefault(PurePosixPath(name).parent.as_posix(), []).append(name)
    folder_means = {folder: mean.compute(folder) for folder in folders}
    return {
        folder: {
            "images": members,
            "models": {n: {m: folder_means[folder][n, m] for m in metric_names} for n in model_names},
        }
        for folder, members in folders.items()
    }


def evaluate_real(
    real_dir: str | os.PathLike,
    metrics=("niqe", "piqe"),
    out_dir: str | os.PathLike = "eval_real",
    weights: list[str] | None = None,
    device: str = "cpu",
    max_samples: int | None = None,
    restorer_factory: Callable[[str, str], Callable[[torch.Tensor], torch.Tensor]] | None = None,
    musiq_weights: str | None = None,
    fail_fast: bool = False,
    on_skip: Callable[[str], None] | None = None,
    recursive: bool = False,
    on_note: Callable[[str], None] | None = None,
) -> dict:
    """Score the images of ``real_dir``; returns the dict written to ``out_dir/results.json``.

    ``results["models"][model][metric] = {"per_image": {file name: value}, "mean": value}`` with one
    model per entry of ``weights`` (default ``["input"]``); ``results[metric]`` repeats the first model's
    entry. ``restorer_factory(weights, device)`` returns ``image (3,H,W) -> restored (3,H,W)``
    (default: ``d2turb.restore.Restorer(weights, device=device).restore``).

    An image that cannot be read, restored or scored is skipped: ``on_skip(message)`` is called, it is
    listed in ``results["skipped"]`` ({"file", "error"}) and left out of the means. With ``fail_fast``
    (or a single image) its ``D2TurbError`` is raised instead; if every image fails, too.

    With ``recursive``, the images of the sub-folders count too: they are named by their path relative to
    ``real_dir`` (``clip/frame.png``), their grids go to ``grids/clip/frame.png``, and
    ``results["folders"][folder] = {"images": [...], "models": {model: {metric: mean}}}`` gives the means per
    folder ("." for ``real_dir`` itself).

    Video files found beside the images are not scored: each is named once, ``on_note(message)`` and
    ``results["not_scored"]`` ({"file", "reason"}), with the command that turns it into frames.
    """
    metric_names = parse_metrics(metrics)
    scorers = {m: no_reference_metric(m, device, musiq_weights) for m in metric_names}
    real_dir = Path(real_dir)
    paths, not_scored = _inputs(real_dir, recursive, max_samples)
    for entry in not_scored:
        if on_note is not None:
            on_note(f"{entry['file']}: not scored, {entry['reason']}")
    relative = [p.relative_to(real_dir) for p in paths]
    names = [r.as_posix() for r in relative]
    weights = list(weights) if weights else [IDENTITY]
    if any(str(w) != IDENTITY for w in weights):
        for folder in dict.fromkeys(r.parent for r in relative):  # grids/<folder>/<stem>.png per image
            check_unique_stems(p for p, r in zip(paths, relative) if r.parent == folder)
    model_names = _model_names(weights)
    factory = restorer_factory or _default_restorer
    restorers = {n: (None if str(w) == IDENTITY else factory(str(w), device)) for n, w in zip(model_names, weights)}

    values = {n: {m: {} for m in metric_names} for n in model_names}  # per image
    mean = KeyedMean(sync_on_compute=False)  # per (model, metric), over all images and per folder
    skipped: list[dict] = []
    out_dir = Path(out_dir)
    for path, rel, name in zip(paths, relative, names):
        try:
            image, outputs, scores = _restore_and_score(path, restorers, scorers)
        except D2TurbError as exc:
            if fail_fast or len(paths) == 1:
                raise
            skipped.append({"file": name, "error": str(exc)})
            if on_skip is not None:
                on_skip(str(exc))
            continue
        for (n, m), value in scores.items():
            values[n][m][name] = value
        mean.update(scores, groups=PurePosixPath(name).parent.as_posix())
        if any(r is not None for r in restorers.values()):
            write_image(
                out_dir / "grids" / rel.with_suffix(".png"),
                _grid(
                    [image, *[outputs[n] for n in model_names if restorers[n] is not None]],
                    ["input", *[n for n in model_names if restorers[n] is not None]],
                ),
            )
    if len(skipped) == len(paths):
        raise D2TurbError(f"{real_dir}: none of the {len(paths)} images could be evaluated")
    names = [n for n in names if n not in {s["file"] for s in skipped}]
    means = mean.compute()
    results = {
        "mode": "real",
        "data": str(real_dir),
        "metrics": metric_names,
        "images": names,
        "skipped": skipped,
        "not_scored": not_scored,
        "models": {n: {m: {"per_image": values[n][m], "mean": means[n, m]} for m in metric_names} for n in model_names},
    }
    results.update({m: results["models"][model_names[0]][m] for m in metric_names})
    if recursive:
        results["folders"] = _folder_means(names, mean, metric_names, model_names)
    write_json(out_dir / "results.json", results)
    write_text(out_dir / "results.md", _markdown(results))
    return results
