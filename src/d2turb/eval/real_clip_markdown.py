"""The tables of the real clips report (:mod:`d2turb.eval.real_clips`): OUT/results.md from results.json."""

from __future__ import annotations

from d2turb.eval.real_clip_measures import COLUMNS, LABELS, TAIL_RISE_MAX


def _estimate_cell(entry: dict) -> str:
    record = entry.get("deblur") or {}
    est = record.get("estimate")
    if not est:
        return "–"
    used = record.get("sigma_px", 0.0)
    text = f"σ {est['sigma_px']:.2f} px ({'confident' if est['confident'] else 'not confident'}); used {used:.2f}"
    if "learned" in record:
        b = record["learned"]
        text = (
            f"learned D/r0 {b['dr0']:.2f}, λ/(D·ifov) {b['lambda_over_d_px']:.2f} px, M {b['modulation']:.2f}; edges "
            + text
        )
    if "lambda_over_d_px" in record:
        text += f", λ/(D·ifov) {record['lambda_over_d_px']:.2f} px"
    return text


def _measure_cells(e: dict, column: str) -> list[str]:
    """near-black, near-white, block, noise, sharpness, ghost cells of one column: the input's values, a method's
    with its change against the input."""
    v, inp = e["measures"][column], e["measures"]["input"]
    if column == "input":
        return [
            f"{v['near_black']:.2f}",
            f"{v['near_white']:.2f}",
            f"{v['block']:.3f}",
            f"{v['noise']:.2f}",
            f"{v['sharpness']:.1f}",
            "–",
        ]
    g = e["ghost"][column]
    return [
        f"{v['near_black']:.2f} ({v['near_black'] - inp['near_black']:+.2f})",
        f"{v['near_white']:.2f} ({v['near_white'] - inp['near_white']:+.2f})",
        f"{v['block']:.3f} ({v['block'] - inp['block']:+.3f})",
        f"{v['noise']:.2f}",
        f"{v['sharpness']:.1f} (×{v['sharpness'] / inp['sharpness']:.2f})",
        f"{g['shaken']:.3f} − {g['calm']:.3f} = {g['excess']:+.3f}",
    ]


def markdown(results: dict) -> str:
    """The report's tables: per clip NIQE / PIQE, residual motion and the blind estimate; per clip and column what a
    person sees (near-black / near-white share, block grid, flat noise, sharpness, the ghost check) and which of
    issue 49's acceptance 3 each method fails."""
    s = results["settings"]
    lines = [
        f"# Real clips report: `{results['data']}`",
        "",
        f"Window {s['temporal']}, first {s['max_frames']} frames per clip; NIQE / PIQE (lower = more natural "
        f"statistics, no ground truth) mean over every {s['score_stride']}th frame; motion: {s['motion']}.",
        "",
        "| clip | frames | NIQE input / mean fusion / --deblur none / default "
        "| PIQE input / mean fusion / --deblur none / default | motion input → none / default (px) "
        "| blind estimate | deblur | note |",
        "|---|---:|---|---|---|---|---|---|",
    ]
    for name, e in results["clips"].items():
        niqe_cell = " / ".join(f"{e['niqe'][c]:.2f}" for c in COLUMNS)
        piqe_cell = " / ".join(f"{e['piqe'][c]:.1f}" for c in COLUMNS)
        m = e["motion_px"]
        motion = f"{m['input']:.3f} → {m['none']:.3f} / {m['default']:.3f}"
        note = (e.get("deblur") or {}).get("note", "")
        lines.append(
            f"| {name} | {e['frames']} | {niqe_cell} | {piqe_cell} | {motion} | {_estimate_cell(e)} "
            f"| {e['deblur_description']} | {note} |"
        )
    lines += [
        "",
        f"What a person sees: {s['measures']}. Ghost check: {s['ghost']}. In brackets: the change against the "
        "input (sharpness: the ratio). Fails: issue 49's acceptance 3 (near-black / near-white share more than "
        f"{TAIL_RISE_MAX} points above the input's, block grid above the input's, a ghost, not sharper).",
        "",
        "| clip (shake: largest shift from the middle frame) | column | near-black % | near-white % | block grid B/A "
        "| flat noise σ | sharpness | ghost share shaken − calm | fails |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, e in results["clips"].items():
        for column in COLUMNS:
            clip = f"{name} ({e['shake']['max_px']:.1f} px)" if column == "input" else ""
            fails = "" if column == "input" else (", ".join(e["checks"][column]) or "none")
            cells = " | ".join(_measure_cells(e, column))
            lines.append(f"| {clip} | {LABELS[column]} | {cells} | {fails} |")
    if results["skipped"]:
        lines += ["", "## Skipped", ""] + [f"- `{s['clip']}`: {s['error']}" for s in results["skipped"]]
    if results["not_clips"]:
        lines += ["", "## Not clips", ""] + [f"- `{n['path']}`: {n['reason']}" for n in results["not_clips"]]
    return "\n".join(lines) + "\n"
