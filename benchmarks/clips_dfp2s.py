"""The default clip restore on clips made by another physics engine: DF-P2S (Chimitt et al., as shipped in
xg416/MambaTM), issue 49 item 5. A check, not a target: nothing is tuned to it.

    # 1. clips: DF-P2S on crops of the test folders, written as a d2turb sequence dataset
    python benchmarks/clips_dfp2s.py make --dfp2s /path/to/MambaTM --clean ../shared/data/clean/bsd100 \
        ../shared/data/clean/sunhays_outdoor --out dfp2s_clips [--per-bin 8] [--frames 24] [--size 256] \
        [--temp-corr 0.5] [--seed 495]
    # 2. the project's own scoring (docs/clips.md): the default and --deblur none
    d2turb evaluate --clips dfp2s_clips --temporal 16 --deblur blind --out ev_default
    d2turb evaluate --clips dfp2s_clips --temporal 16 --fusion sharpest --deblur none --out ev_none
    # 3. per bin: mean ± standard error over clips, paired differences; one JSON object
    python benchmarks/clips_dfp2s.py summarise --default ev_default --none ev_none [--clips dfp2s_clips] [--json FILE]
    # 4. the figure: one clip's frames for `d2turb restore`, then clean | DF-P2S | d2turb sim | --deblur none | default
    python benchmarks/clips_dfp2s.py frames --clips dfp2s_clips --id 0 --out frames/0000000
    python benchmarks/clips_dfp2s.py figure --clips dfp2s_clips --ids 0000000 ... --restored DIR --out fig.jpg

Results, settings and the commands run: docs/clips_dfp2s.md.

DF-P2S is not a dependency and none of its code is in d2turb: ``--dfp2s`` is a MambaTM checkout (or its
``code/LPD_learning`` folder, holding ``utils/simulator.py`` and the pretrained ``utils/precomputed/*``), imported
from that path. Its settings: D = 0.1 m, λ = 525 nm, L = 1 km, Nyquist pixels (ifov = λ/2D, as the project's
``field`` geometry), 36 Zernike modes, a constant Cn² over 10 layers chosen by inverting DF-P2S's own r0 formula so
that its D/r0 is the clip's (drawn uniformly inside the project's bin: weak [1, 2.25), medium [2.25, 3.75], strong
(3.75, 5]), its own kernel-size rule (``bench_dfp2s.dfp2s_kernel_size``), frames made one after another with its AR(1)
temporal correlation ``temp_corr`` (``--temp-corr``). Turbulence on the 8-bit values as read (as the project's
test and blind sets), then rounded to 8 bits; no camera noise or codec.

Dataset layout (docs/datasets.md, "Sequences"): ``turb/`` and ``tilt/`` filmstrips, ``gt/`` the clean crop,
``depth/`` flat (DF-P2S has no depth), ``bwd_flow_px/`` = −(DF-P2S's tilt field) in px (x, y): DF-P2S samples
tilt(x) = clean(x + t(x)), so gt(x) ≈ tilt(x − t(x)) to first order (only the EPE columns read it). Clip i: bin
``bins[i % 3]``, source image ``(i // 3) · stride`` of the sorted test images (stride spreads the clips over both
folders), D/r0, crop and DF-P2S's noise from (seed, i) alone.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dfp2s import RANGE, WAVELENGTH, D, dfp2s_folder, dfp2s_params  # noqa: E402

from d2turb.data.layout import write_depth_png  # noqa: E402
from d2turb.data.sequence import SequenceDataset  # noqa: E402
from d2turb.data.split import split_of  # noqa: E402
from d2turb.io import list_images, read_image, write_image, write_json, write_npy, write_text  # noqa: E402
from d2turb.sim.params import BINS  # noqa: E402

LAYERS = 10
BIN_NAMES = tuple(BINS)  # weak, medium, strong; BINS their D/r0 ranges
ROWS = {"input frames": "input", "--deblur none": "fused", "default": "fused + blind"}


def make_sim(folder: Path, size: int, dr0: float, temp_corr: float):
    """A DF-P2S simulator of one frame per call (frames in sequence: AR(1) seeds), at D/r0 ``dr0``."""
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    from utils.simulator import Simulator as DFP2S  # noqa: PLC0415  (third-party code, imported from its path)

    params, cn2 = dfp2s_params(size, 1, dr0, temp_corr, LAYERS)
    sim = DFP2S(str(folder / "utils"), params, Batch_unrelated=1)
    return sim, {"cn2": cn2, "kernel_size": params["kernel_size"], "dfp2s_dr0": float(sim.Dr0)}


def _filmstrip(frames: list[torch.Tensor]) -> np.ndarray:
    """(N, 3, H, W) in [0, 1] → (N·H, W, 3) uint8."""
    x = torch.stack(frames).clamp(0, 1).mul(255).round().to(torch.uint8)
    return x.permute(0, 2, 3, 1).reshape(-1, x.shape[-1], 3).numpy()


def make(args) -> int:
    folder = dfp2s_folder(args.dfp2s)
    if folder is None:
        print(f"error: no DF-P2S checkout at {args.dfp2s!r}", file=sys.stderr)
        return 2
    for c in args.clean:
        if split_of(c) != "test":
            print(f"error: {c} is not a test folder (docs/training.md)", file=sys.stderr)
            return 2
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)  # DF-P2S asks for it on CPU
    images = [p for c in args.clean for p in list_images(c)]
    n = args.per_bin * len(BIN_NAMES)
    stride = max(1, len(images) // args.per_bin)
    out = Path(args.out)
    for sub in ("turb", "tilt", "gt", "depth", "bwd_flow_px"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    s = args.size
    config = {
        "version": 1,
        "engine": "DF-P2S (xg416/MambaTM code/LPD_learning/utils/simulator.py)",
        "patch": s,
        "pairs": 0,
        "frames": args.frames,
        "split": "test",
        "bins": list(BIN_NAMES),
        "bin_ranges": {k: list(v) for k, v in BINS.items()},
        "clean": [str(c) for c in args.clean],
        "seed": args.seed,
        "temp_corr": args.temp_corr,
        "optics": {"aperture_m": D, "wavelength_m": WAVELENGTH, "path_length_m": RANGE, "ifov_rad": WAVELENGTH / 2 / D},
        "layers": LAYERS,
        "depth": "none (flat)",
        "depth_encoding": "16-bit PNG, depth = value / 65535, far = 1",
        "bwd_flow_px": "float16 (N,2,H,W): minus DF-P2S's tilt in px, x then y (first order)",
        "files": {k: f"{k}/<id>.{'npy' if k == 'bwd_flow_px' else 'png'}" for k in ("turb", "tilt", "gt", "depth")}
        | {"bwd_flow_px": "bwd_flow_px/<id>.npy"},
    }
    records = []
    if (out / "meta.jsonl").is_file():  # resume: clips are drawn from (seed, i) alone
        old = json.loads((out / "dataset.json").read_text())
        if {k: old.get(k) for k in ("patch", "frames", "seed", "temp_corr", "clean")} != {
            k: config[k] for k in ("patch", "frames", "seed", "temp_corr", "clean")
        }:
            print(f"error: {out} holds clips made with other settings", file=sys.stderr)
            return 2
        records = [json.loads(line) for line in (out / "meta.jsonl").read_text().splitlines() if line.strip()]
    done = {r["index"] for r in records}
    t0 = time.perf_counter()
    for i in range(n):
        if i in done:
            continue
        rng = np.random.default_rng([args.seed, i])
        name = BIN_NAMES[i % len(BIN_NAMES)]
        lo, hi = BINS[name]
        dr0 = float(rng.uniform(lo, hi))
        src = images[((i // len(BIN_NAMES)) * stride) % len(images)]
        clean = read_image(src)
        h, w = clean.shape[-2:]
        y0, x0 = int(rng.integers(0, h - s + 1)), int(rng.integers(0, w - s + 1))
        gt = clean[:, y0 : y0 + s, x0 : x0 + s].contiguous()
        torch.manual_seed(int(rng.integers(0, 2**62)))
        sim, info = make_sim(folder, s, dr0, args.temp_corr)
        turb, tilt, flow = [], [], []
        with torch.no_grad():
            for _ in range(args.frames):
                out_f, tilt_f, zer = sim(gt[None], require_tilt=True)
                turb.append(out_f[0])
                tilt.append(tilt_f[0])
                flow.append(-zer[0, :, :, :2].permute(2, 0, 1))  # (2, H, W), x then y
        sid = f"{i:07d}"
        write_image(out / "turb" / f"{sid}.png", _filmstrip(turb))
        write_image(out / "tilt" / f"{sid}.png", _filmstrip(tilt))
        write_image(out / "gt" / f"{sid}.png", _filmstrip([gt]))
        write_depth_png(out / "depth" / f"{sid}.png", torch.ones(1, s, s))
        write_npy(out / "bwd_flow_px" / f"{sid}.npy", torch.stack(flow).numpy().astype(np.float16))
        tilt_rms = float(torch.stack(flow).pow(2).mean().sqrt())
        records.append(
            {
                "id": sid,
                "index": i,
                "bin": name,
                "dr0": dr0,
                "source": str(src),
                "crop": [x0, y0, x0 + s, y0 + s],
                "split": "test",
                "engine": "DF-P2S",
                "dfp2s": info | {"temp_corr": args.temp_corr, "tilt_rms_px": tilt_rms},
                "params": {"aperture_m": D, "wavelength_m": WAVELENGTH, "path_length_m": RANGE},
            }
        )
        # the dataset is valid after every clip: a run stopped early leaves the clips made so far
        write_text(out / "meta.jsonl", "".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
        write_json(
            out / "dataset.json", config | {"pairs": len(records), "seconds": round(time.perf_counter() - t0, 1)}
        )
        print(
            json.dumps({"clip": sid, "bin": name, "dr0": round(dr0, 3), "tilt_rms_px": round(tilt_rms, 2)})
            + f"  {time.perf_counter() - t0:.0f} s",
            flush=True,
        )
    return 0


def _mean_se(values) -> dict:
    v = np.asarray(values, dtype=np.float64)
    se = round(float(v.std(ddof=1) / math.sqrt(len(v))), 3) if len(v) > 1 else None
    return {"mean": round(float(v.mean()), 3), "se": se, "n": len(v)}


def _blind(record: dict) -> dict:
    """What the default's blind deblur did on a clip: the σ it applied (0: none), its learned estimate of D/r0 and
    λ/(D·ifov) (the truth here: the clip's D/r0 and 2 px), the λ/(D·ifov) it deblurred at, and its note."""
    learned = record.get("learned", {})
    return {
        "sigma_px": record.get("sigma_px"),
        "learned_dr0": learned.get("dr0"),
        "learned_lambda_over_d_px": learned.get("lambda_over_d_px"),
        "lambda_over_d_px": record.get("lambda_over_d_px"),
        "fused_edge_sigma_px": record.get("estimate", {}).get("sigma_px"),  # the fused frame's blur, from its edges
        "note": record.get("note", ""),
    }


def _tilt_stats(root: Path, ids: list[str]) -> dict:
    """Per bin, from the clips' ``bwd_flow_px``: rms tilt (px, both axes), rms after removing each frame's mean (the
    part a global offset cannot remove) and the frame-to-frame correlation of the tilt."""
    rms, local, lag1 = [], [], []
    for sid in ids:
        f = np.load(root / "bwd_flow_px" / f"{sid}.npy").astype(np.float64)
        rms.append(np.sqrt((f**2).mean()))
        fl = f - f.mean(axis=(2, 3), keepdims=True)
        local.append(np.sqrt((fl**2).mean()))
        a, b = f[:-1], f[1:]
        lag1.append((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))
    return {"rms_px": _mean_se(rms), "local_rms_px": _mean_se(local), "lag1_corr": _mean_se(lag1)}


def summarise(args) -> int:
    runs = {}
    for k, folders in (("default", args.default), ("none", args.none)):  # one or more parts of the same set
        parts = [json.loads((Path(p) / "results.json").read_text()) for p in folders]
        runs[k] = parts[0] | {"samples": [x for r in parts for x in r["samples"]]}
    by_id = {k: {s["id"]: s for s in r["samples"]} for k, r in runs.items()}
    # (run, row of evaluate --clips): the input frames and the raw mean are the same in both runs (same frames)
    rows = {
        "input frames": ("default", "input"),
        "temporal mean (unregistered)": ("default", "temporal mean"),
        "mean fusion, no deblur": ("default", "fused"),
        "--deblur none (sharpest fusion)": ("none", "fused"),
        "default (mean fusion + blind deblur)": ("default", "fused + blind"),
    }
    report = {
        "benchmark": "clips_dfp2s",
        "dataset": runs["default"]["dataset"],
        "default_run": runs["default"]["settings"],
        "none_run": runs["none"]["settings"],
        "bins": {},
    }
    for b in BIN_NAMES:
        ids = [s["id"] for s in runs["default"]["samples"] if s["bin"] == b]
        if not ids:
            continue
        row = {"clips": len(ids), "dr0": _mean_se([by_id["default"][i]["dr0"] for i in ids])}
        for metric in ("psnr_aligned", "ssim_aligned", "psnr", "cwssim"):
            vals = {name: [by_id[run][i][f"{r} {metric}"] for i in ids] for name, (run, r) in rows.items()}
            inp, none, default = (vals[k] for k in ("input frames", *list(rows)[3:]))
            row[metric] = {k: _mean_se(v) for k, v in vals.items()}
            row[metric]["default − input"] = _mean_se(np.subtract(default, inp))
            row[metric]["--deblur none − input"] = _mean_se(np.subtract(none, inp))
            row[metric]["default − --deblur none"] = _mean_se(np.subtract(default, none))
            if metric == "psnr_aligned":
                d = np.subtract(default, none)
                row["clips_default_below_none"] = int((d < 0).sum())
                row["worst_default_minus_none_db"] = round(float(d.min()), 3)
        row["epe_vs_observable_px"] = _mean_se([by_id["default"][i]["epe"] for i in ids])
        row["epe_of_zero_px"] = _mean_se([by_id["default"][i]["epe_zero"] for i in ids])
        blind = [_blind(by_id["default"][i].get("blind", {})) for i in ids]
        row["blind_deblurred_clips"] = sum(1 for x in blind if x["sigma_px"])
        for key in ("learned_dr0", "learned_lambda_over_d_px", "fused_edge_sigma_px"):
            vals = [x[key] for x in blind if x[key] is not None]
            row[key] = _mean_se(vals) if vals else None
        row["blind"] = blind
        if args.clips:
            row["tilt"] = _tilt_stats(Path(args.clips), ids)
        report["bins"][b] = row
    print(json.dumps(report, indent=2, ensure_ascii=False))
    print(markdown(report))
    if args.json:
        write_json(args.json, report)
    return 0


def _pm(m: dict, fmt: str) -> str:
    se = "–" if m["se"] is None else format(m["se"], fmt.lstrip("+"))
    return f"{format(m['mean'], fmt)} ± {se}"


def markdown(report: dict) -> str:
    """The offset-removed PSNR / SSIM per bin: mean ± standard error (n clips), gains over the input frames."""
    bins = report["bins"]
    lines = ["| offset-removed PSNR (dB) | " + " | ".join(f"{b} (n={bins[b]['clips']})" for b in bins) + " |"]
    lines.append("|---|" + "---:|" * len(bins))
    for name in bins[next(iter(bins))]["psnr_aligned"]:
        cells = []
        for b in bins:
            m = bins[b]["psnr_aligned"][name]
            cells.append(_pm(m, "+.2f" if "−" in name else ".2f"))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "| offset-removed SSIM | " + " | ".join(bins) + " |", "|---|" + "---:|" * len(bins)]
    for name in bins[next(iter(bins))]["ssim_aligned"]:
        cells = [_pm(bins[b]["ssim_aligned"][name], "+.3f" if "−" in name else ".3f") for b in bins]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def frames(args) -> int:
    """Write clip ``--id``'s frames as ``frame_NNN.png`` into ``--out`` (the input of ``d2turb restore``)."""
    item = SequenceDataset(args.clips)[int(args.id)]
    Path(args.out).mkdir(parents=True, exist_ok=True)
    for t, f in enumerate(item["turb"]):
        write_image(Path(args.out) / f"frame_{t:03d}.png", f)
    return 0


def figure(args) -> int:
    """Per clip (one row each): the clean crop, DF-P2S's frame, d2turb's simulator on the same crop at the same D/r0
    (Nyquist pixels, no depth), the ``restore --deblur none`` and the default output of that frame (folders
    ``RESTORED/<id>/none`` and ``RESTORED/<id>/default``); also scores every 4th restored frame as ``evaluate
    --clips`` does (offset removed), to check that the CLI and ``evaluate`` agree."""
    from PIL import Image, ImageDraw  # noqa: PLC0415

    from d2turb.eval.clips import remove_global_offset  # noqa: PLC0415
    from d2turb.eval.metrics import psnr  # noqa: PLC0415
    from d2turb.sim import Simulator, TurbulenceParams  # noqa: PLC0415

    torch.set_num_threads(1)
    data = SequenceDataset(args.clips)
    tiles, scores = [], {}
    for sid in args.ids:
        idx = next(k for k, r in enumerate(data.records) if r["id"] == sid)
        item, rec = data[idx], data.records[idx]
        t = args.frame
        gt = item["gt"]
        sim = Simulator(TurbulenceParams(dr0=float(rec["dr0"]), ifov_rad=WAVELENGTH / 2 / D))
        ours = sim(gt[None], generator=torch.Generator().manual_seed(int(sid))).turb[0]
        restored = {}
        for kind in ("none", "default"):
            folder = Path(args.restored) / sid / kind
            files = sorted(folder.glob("frame_*_restored.png"))
            restored[kind] = [read_image(f) for f in files]
            vals = []
            for k in range(0, len(files), 4):
                moved, ref, _ = remove_global_offset(restored[kind][k].clamp(0, 1), gt)
                vals.append(float(psnr(moved[None], ref[None])))
            scores[f"{sid} {kind}"] = round(float(np.mean(vals)), 3)
        row = [gt, item["turb"][t], ours.clamp(0, 1), restored["none"][t], restored["default"][t]]
        tiles.append(torch.cat(row, dim=-1))
    img = torch.cat(tiles, dim=-2).clamp(0, 1).mul(255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    s = data.patch
    labels = ["clean", f"DF-P2S frame {args.frame}", "d2turb sim, same D/r0", "--deblur none", "default"]
    for c, text in enumerate(labels):
        for r in range(len(args.ids)):
            draw.rectangle([c * s, r * s, c * s + 7 * len(text) + 6, r * s + 14], fill=(0, 0, 0))
            draw.text((c * s + 3, r * s + 2), text, fill=(255, 255, 255))
    for r, sid in enumerate(args.ids):
        rec = next(x for x in data.records if x["id"] == sid)
        text = f"{rec['bin']} D/r0 {rec['dr0']:.2f}"
        draw.rectangle([0, r * s + s - 15, 7 * len(text) + 6, r * s + s], fill=(0, 0, 0))
        draw.text((3, r * s + s - 13), text, fill=(255, 255, 255))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    pil.save(args.out, quality=90)
    print(json.dumps({"cli_offset_removed_psnr_every_4th_frame": scores}, indent=2))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make", help="DF-P2S clips as a d2turb sequence dataset")
    m.add_argument("--dfp2s", required=True, help="MambaTM checkout (or its code/LPD_learning folder)")
    m.add_argument("--clean", nargs="+", required=True, help="test folders of the fixed split")
    m.add_argument("--out", required=True)
    m.add_argument("--per-bin", type=int, default=8)
    m.add_argument("--frames", type=int, default=24)
    m.add_argument("--size", type=int, default=256)
    m.add_argument("--temp-corr", type=float, default=0.5, help="DF-P2S's AR(1) frame-to-frame correlation")
    m.add_argument("--seed", type=int, default=495)
    m.set_defaults(func=make)
    s = sub.add_parser("summarise", help="per-bin means ± standard errors of two evaluate --clips runs")
    s.add_argument("--default", nargs="+", required=True, help="evaluate --clips --deblur blind output folder(s)")
    s.add_argument(
        "--none", nargs="+", required=True, help="evaluate --clips --fusion sharpest --deblur none output folder(s)"
    )
    s.add_argument("--clips", default=None, help="the dataset: adds the tilt statistics of each bin")
    s.add_argument("--json", default=None, metavar="FILE")
    s.set_defaults(func=summarise)
    f = sub.add_parser("frames", help="one clip's frames as PNG files (for d2turb restore)")
    f.add_argument("--clips", required=True)
    f.add_argument("--id", required=True, help="clip index")
    f.add_argument("--out", required=True)
    f.set_defaults(func=frames)
    g = sub.add_parser("figure", help="clean | DF-P2S | d2turb sim | --deblur none | default, one row per clip")
    g.add_argument("--clips", required=True)
    g.add_argument("--ids", nargs="+", required=True, help="clip ids (e.g. 0000000)")
    g.add_argument("--restored", required=True, help="folder with <id>/none and <id>/default restore outputs")
    g.add_argument("--frame", type=int, default=12)
    g.add_argument("--out", required=True, help="figure file (.jpg)")
    g.set_defaults(func=figure)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
