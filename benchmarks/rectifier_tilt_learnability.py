"""Is the tilt learnable from one frame, and where? (issue 51, item 1)

A rectifier-only experiment: d2turb-small's rectifier (the authors' design at half width, 16/32/64/128/128/128,
no injection: there is no backbone) is trained with the paper's L_flow (mean |V̂ − V_bwd|, px) to predict the
simulator's true backward flow V_bwd from the tilted-but-sharp frame I_tilt (the deblurring stage's target, so the
best case of what D²Turb's rectifier sees), on small crops synthesised on the fly ("field" geometries, the three
strength bins, the weight-free depth prior). It is scored by the end-point error (mean over pixels of ‖V̂ − V_bwd‖₂)
on held-out crops of the validation and test folders (set14, mcmaster, bsd100, sunhays_outdoor) and of synthetic
charts and text from seeds never trained on, against zero flow (the identity warp), beside the size of each crop's
mean displacement ‖mean V_bwd‖ (what no single frame can reveal: a scene moved as a whole looks like another scene,
so even a perfect estimator of the rest errs by it), the best constant flow (that mean, known) and, with ``--dis``,
OpenCV's DIS optical flow given the clean crop too (the flow recovered by registration).

Held-out crops are split by a structure score fixed before any model was scored: the total length of the straight
segments OpenCV's line segment detector finds in the clean crop (segments ≥ 20 px), in crop widths. ``structured``:
≥ 2 crop widths; ``natural``: < 0.5; ``mixed`` in between (of 300 random 96² crops, urban100's are 81 % structured
and 6 % natural, bsds500's 28 % and 34 %). Standard errors are over images (each image's crops are
averaged first), so crops of one image are not counted as independent.

    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/rectifier_tilt_learnability.py --name mixed --minutes 12
    ... --name oracle --oracle --minutes 12   # the rectifier also sees the clean image: the flow is a registration
    ... --name dis --dis                       # no training: DIS given the clean image
    ... --name sizes --sizes                   # no training: the crop-mean share of the flow at 64² ... 256²
    ... --table benchmarks/results/rectifier_tilt_{dis,mixed,oracle}.json     # the table of docs/training.md

Writes benchmarks/results/rectifier_tilt_<name>.json (config, training curve, per-category, -folder and -bin
summaries; ``--rows``: every held-out crop's row too, as in the commit that first added these files);
``--cache DIR`` keeps the decoded images and depth priors between runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from d2turb.data import OnTheFlySynthesis
from d2turb.depth.prior import estimate_depth_prior
from d2turb.io import read_image
from d2turb.models.rectifier import TiltRectifier
from d2turb.sim import Simulator
from d2turb.sim.geometry import geometry_bank

ROOT = Path(__file__).resolve().parents[1]
CLEAN = ROOT.parent / "shared" / "data" / "clean"
TRAIN = {
    "structured": ["urban100", "strecha_mvs", "sfm_landmarks", "camvid"],
    "natural": ["bsds500", "t91"],
}
HELD_OUT = ["set14", "mcmaster", "bsd100", "sunhays_outdoor"]  # the val and test folders of the fixed split
WIDTHS = (16, 32, 64, 128, 128, 128)  # d2turb-small's rectifier
LINE_MIN_PX = 20.0
STRUCTURED_WIDTHS, NATURAL_WIDTHS = 2.0, 0.5  # structure score thresholds (crop widths of straight segments)
_LSD = cv2.createLineSegmentDetector()


# ----------------------------------------------------------------------------------------------- data
class Images:
    """Clean images (uint8, long side ≤ ``max_side``) and their depth priors (float16), held in memory."""

    def __init__(self, folders: list[str], max_side: int, patch: int, cache: Path | None = None):
        key = cache / f"images_{'+'.join(folders)}_{max_side}_{patch}.pt" if cache else None
        if key is not None and key.is_file():
            self.names, self.images, self.depths = torch.load(key, weights_only=True).values()
            return
        self.names, self.images, self.depths = [], [], []
        for folder in folders:
            for path in sorted((CLEAN / folder).iterdir()):
                if path.suffix.lower() not in (".jpg", ".jpeg", ".png", ".bmp"):
                    continue
                img = read_image(path)
                h, w = img.shape[-2:]
                s = min(1.0, max_side / max(h, w))
                if min(h, w) * s < patch:
                    s = patch / min(h, w)
                if s != 1.0:
                    size = (max(patch, round(h * s)), max(patch, round(w * s)))
                    img = torch.nn.functional.interpolate(img[None], size=size, mode="area")[0]
                self.names.append(f"{folder}/{path.name}")
                self.images.append((img.clamp(0, 1) * 255).round().to(torch.uint8))
                self.depths.append(estimate_depth_prior(img).to(torch.float16))
        if key is not None:
            key.parent.mkdir(parents=True, exist_ok=True)
            tmp = key.with_suffix(f".{os.getpid()}.tmp")
            torch.save({"names": self.names, "images": self.images, "depths": self.depths}, tmp)
            tmp.replace(key)

    def crops(self, rng: np.random.Generator, n: int, patch: int, flip: bool) -> tuple[dict, list[int]]:
        idx = rng.integers(len(self.images), size=n).tolist()
        gts, depths = [], []
        for i in idx:
            img, dep = self.images[i], self.depths[i]
            h, w = img.shape[-2:]
            y, x = int(rng.integers(h - patch + 1)), int(rng.integers(w - patch + 1))
            g, d = img[:, y : y + patch, x : x + patch], dep[:, y : y + patch, x : x + patch]
            if flip and rng.random() < 0.5:
                g, d = g.flip(-1), d.flip(-1)
            gts.append(g.float() / 255)
            depths.append(d.float())
        return {"gt": torch.stack(gts), "depth": torch.stack(depths)}, idx


def chart(rng: np.random.Generator, patch: int) -> np.ndarray:
    """A synthetic chart, text or grid (RGB float32 in [0, 1]), drawn in 8 bits at 2x, area-downscaled."""
    s = 2 * patch
    img = np.empty((s, s, 3), np.uint8)
    img[:] = rng.integers(150, 256, 3)
    ink = lambda: tuple(int(v) for v in rng.integers(0, 115, 3))  # noqa: E731
    kind = rng.integers(4)
    if kind == 0:  # text lines
        fonts = [cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_PLAIN]
        scale = rng.uniform(0.4, 1.2)
        step = int(28 * scale) + int(rng.integers(4, 14))
        y = int(rng.integers(10, 30))
        chars = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789 .,:-"
        while y < s + 20:
            text = "".join(rng.choice(list(chars), size=int(rng.integers(8, 30))))
            cv2.putText(img, text, (int(rng.integers(-20, 10)), y), fonts[rng.integers(4)], scale, ink(),
                        int(rng.integers(1, 3)), cv2.LINE_AA)  # fmt: skip
            y += step
    elif kind == 1:  # bar chart with axes, ticks and grid lines
        colour = ink()
        x0, y0 = int(rng.integers(10, 40)), s - int(rng.integers(10, 40))
        for gy in range(y0, 0, -int(rng.integers(16, 40))):
            cv2.line(img, (x0, gy), (s, gy), tuple((c + 255) // 2 for c in colour), 1, cv2.LINE_AA)
        x = x0 + 6
        while x < s:
            bw = int(rng.integers(8, 30))
            cv2.rectangle(img, (x, int(rng.integers(10, y0 - 5))), (x + bw, y0), ink(), -1, cv2.LINE_AA)
            x += bw + int(rng.integers(3, 15))
        cv2.line(img, (x0, 0), (x0, y0), colour, 2, cv2.LINE_AA)
        cv2.line(img, (x0, y0), (s, y0), colour, 2, cv2.LINE_AA)
    elif kind == 2:  # a rotated grid or checkerboard
        period = rng.uniform(6, 30)
        ang = rng.uniform(0, math.pi)
        yy, xx = np.mgrid[0:s, 0:s].astype(np.float32)
        u = (xx * math.cos(ang) + yy * math.sin(ang)) / period
        v = (-xx * math.sin(ang) + yy * math.cos(ang)) / period
        if rng.random() < 0.5:
            mask = (np.floor(u) + np.floor(v)) % 2 == 0
        else:
            mask = (np.abs(u - np.round(u)) < 0.12) | (np.abs(v - np.round(v)) < 0.12)
        img[mask] = ink()
    else:  # line drawing: polylines, rectangles, circles
        for _ in range(int(rng.integers(6, 20))):
            p = rng.integers(0, s, size=(2, 2))
            shape = rng.integers(3)
            if shape == 0:
                cv2.line(img, tuple(map(int, p[0])), tuple(map(int, p[1])), ink(), int(rng.integers(1, 4)), cv2.LINE_AA)
            elif shape == 1:
                cv2.rectangle(img, tuple(map(int, p[0])), tuple(map(int, p[1])), ink(), int(rng.integers(1, 4)))
            else:
                cv2.circle(img, tuple(map(int, p[0])), int(rng.integers(4, s // 3)), ink(), int(rng.integers(1, 4)),
                           cv2.LINE_AA)  # fmt: skip
    return cv2.resize(img, (patch, patch), interpolation=cv2.INTER_AREA).astype(np.float32) / 255


def charts(rng: np.random.Generator, n: int, patch: int) -> dict:
    gt = torch.from_numpy(np.stack([chart(rng, patch) for _ in range(n)])).permute(0, 3, 1, 2).contiguous()
    return {"gt": gt, "depth": torch.ones(n, 1, patch, patch)}  # a flat target at the far end


def structure_score(gt: torch.Tensor) -> float:
    """Total length of straight segments (LSD, ≥ LINE_MIN_PX) in the clean crop (3,H,W), in crop widths."""
    grey = cv2.cvtColor((gt.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
    lines = _LSD.detect(grey)[0]
    if lines is None:
        return 0.0
    seg = lines.reshape(-1, 4)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    return float(length[length >= LINE_MIN_PX].sum() / gt.shape[-1])


def category(score: float) -> str:
    return "structured" if score >= STRUCTURED_WIDTHS else "natural" if score < NATURAL_WIDTHS else "mixed"


# ----------------------------------------------------------------------------------------------- model
def model_input(batch: dict, oracle: bool, source: str) -> torch.Tensor:
    x = batch[source]
    return torch.cat([x, batch["gt"]], 1) if oracle else x


def epe_map(flow: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,2,H,W) → per-crop mean end-point error (B,)."""
    return (flow - target).norm(dim=1).flatten(1).mean(1)


# ----------------------------------------------------------------------------------------------- eval set
def build_eval(args, synth_seed: int) -> list[dict]:
    """Fixed held-out batches: crops of the val/test folders and synthetic charts from other seeds."""
    sims = [Simulator(p, "cpu") for p in geometry_bank("field", {})]
    synth = OnTheFlySynthesis(sims, bins=("weak", "medium", "strong"), seed=synth_seed, use_depth=True)
    rng = np.random.default_rng(10_000 + synth_seed)
    held = Images(HELD_OUT, args.max_side, args.patch, args.cache)
    per_image = max(1, args.eval_crops // len(held.images))
    out = []
    order = [i for i in range(len(held.images)) for _ in range(per_image)]
    for start in range(0, len(order), args.batch):
        idx = order[start : start + args.batch]
        gts, deps = [], []
        for i in idx:
            img, dep = held.images[i], held.depths[i]
            h, w = img.shape[-2:]
            y, x = int(rng.integers(h - args.patch + 1)), int(rng.integers(w - args.patch + 1))
            gts.append(img[:, y : y + args.patch, x : x + args.patch].float() / 255)
            deps.append(dep[:, y : y + args.patch, x : x + args.patch].float())
        b = synth({"gt": torch.stack(gts), "depth": torch.stack(deps)})
        out.append(_keep(b, [held.names[i] for i in idx]))
    for start in range(0, args.eval_charts, args.batch):
        n = min(args.batch, args.eval_charts - start)
        b = synth(charts(np.random.default_rng([7, synth_seed, start]), n, args.patch))
        out.append(_keep(b, [f"charts/{start + k}" for k in range(n)]))
    return out


def _keep(b: dict, names: list[str]) -> dict:
    scores = [structure_score(g) for g in b["gt"]]
    cats = ["charts" if n.startswith("charts/") else category(s) for n, s in zip(names, scores)]
    return {
        "tilt": b["tilt"],
        "turb": b["turb"],
        "gt": b["gt"],
        "flow": b["bwd_flow_px"],
        "names": names,
        "score": scores,
        "cat": cats,
        "bin": [int(v) for v in b["bin"]],
    }


@torch.no_grad()
def evaluate(net, eval_set, args) -> list[dict]:
    """Per held-out crop: EPE of the model (``net`` None: DIS given the clean image), of zero, of the best constant."""
    if net is not None:
        net.eval()
    rows = []
    for b in eval_set:
        if net is None:
            pred = torch.stack([dis_flow(g, t) for g, t in zip(b["gt"], b["tilt"])])
        else:
            x = model_input(b, args.oracle, args.source)
            pred = net(x, torch.zeros(x.shape[0], 1, *x.shape[-2:]))
        target = b["flow"]
        mean = target.mean(dim=(2, 3), keepdim=True).expand_as(target)
        for k, (e, z, c) in enumerate(zip(epe_map(pred, target), epe_map(0 * target, target), epe_map(mean, target))):
            rows.append(
                {
                    "image": b["names"][k],
                    "folder": b["names"][k].split("/")[0],
                    "cat": b["cat"][k],
                    "score": round(b["score"][k], 3),
                    "bin": b["bin"][k],
                    "epe": float(e),
                    "epe_zero": float(z),
                    "epe_const": float(c),
                    "mean_px": float(target[k].mean(dim=(1, 2)).norm()),  # EPE of the flow minus its crop mean
                }
            )
    if net is not None:
        net.train()
    return rows


def dis_flow(gt: torch.Tensor, tilt: torch.Tensor) -> torch.Tensor:
    """OpenCV's DIS optical flow from the clean crop to the tilted one, (3,H,W) each → (2,H,W): the V with
    tilt(x + V(x)) ≈ gt(x), i.e. the backward flow, recovered by registration when the clean image is known."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    grey = lambda t: cv2.cvtColor((t.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)  # noqa: E731
    return torch.from_numpy(dis.calc(grey(gt), grey(tilt), None)).permute(2, 0, 1)


def summarise(rows: list[dict], key) -> dict:
    """Per group: crops, images, mean EPE (model, zero, best constant) and the paired difference model − zero with its
    standard error over images (each image's crops averaged first)."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(key(r), []).append(r)
    out = {}
    for g, rs in sorted(groups.items()):
        by_img: dict[str, list[dict]] = {}
        for r in rs:
            by_img.setdefault(r["image"], []).append(r)
        diff = np.array([np.mean([r["epe"] - r["epe_zero"] for r in v]) for v in by_img.values()])
        rel = np.array([np.mean([r["epe"] / r["epe_zero"] for r in v]) for v in by_img.values()])
        n = len(diff)
        se = lambda a: float(a.std(ddof=1) / math.sqrt(len(a))) if len(a) > 1 else float("nan")  # noqa: E731
        out[g] = {
            "crops": len(rs),
            "images": n,
            "epe": float(np.mean([r["epe"] for r in rs])),
            "epe_zero": float(np.mean([r["epe_zero"] for r in rs])),
            "epe_const": float(np.mean([r["epe_const"] for r in rs])),
            "mean_px": float(np.mean([r.get("mean_px", np.nan) for r in rs])),
            "diff": float(diff.mean()),
            "diff_se": se(diff),
            "ratio": float(rel.mean()),
            "ratio_se": se(rel),
        }
    return out


def mean_share_by_size(args, sizes=(64, 96, 128, 256), batches: int = 8) -> dict:
    """No training: on held-out crops of each size, the zero-flow EPE, the size of the crop's mean displacement and
    the EPE of the flow minus that mean (``batches`` × ``args.batch`` crops per size, seed 5)."""
    held = Images(HELD_OUT, args.max_side, args.patch, args.cache)
    sims = [Simulator(p, "cpu") for p in geometry_bank("field", {})]
    out = {}
    for size in sizes:
        synth = OnTheFlySynthesis(sims, bins=("weak", "medium", "strong"), seed=5, use_depth=True)
        ok = [i for i, im in enumerate(held.images) if min(im.shape[-2:]) >= size]
        rng = np.random.default_rng(size)
        zero, mean_px, const = [], [], []
        for _ in range(batches):
            gts, deps = [], []
            for i in rng.choice(ok, args.batch):
                im, d = held.images[i], held.depths[i]
                h, w = im.shape[-2:]
                y, x = rng.integers(h - size + 1), rng.integers(w - size + 1)
                gts.append(im[:, y : y + size, x : x + size].float() / 255)
                deps.append(d[:, y : y + size, x : x + size].float())
            flow = synth({"gt": torch.stack(gts), "depth": torch.stack(deps)})["bwd_flow_px"]
            mean = flow.mean(dim=(2, 3), keepdim=True)
            zero += epe_map(0 * flow, flow).tolist()
            mean_px += mean.flatten(1).norm(dim=1).tolist()
            const += epe_map(mean.expand_as(flow), flow).tolist()
        out[size] = {
            "crops": len(zero),
            "epe_zero": float(np.mean(zero)),
            "mean_px": float(np.mean(mean_px)),
            "epe_const": float(np.mean(const)),
            "mean_share": float(np.mean(mean_px) / np.mean(zero)),
        }
        print(size, json.dumps(out[size]), flush=True)
    return out


def write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(obj, separators=(",", ":")))
    tmp.replace(path)


# ----------------------------------------------------------------------------------------------- table
def table(paths: list[Path]) -> str:
    """The markdown table of docs/training.md from result files (the same held-out crops in each): per category,
    crops (images), EPE of zero flow and of its crop-mean part, then each run's EPE as a ratio to zero flow ± s.e."""
    runs = [json.loads(p.read_text()) for p in paths]
    head = "| held-out crops | n crops (images) | EPE zero flow (px) | its crop mean: ‖mean V‖ (px) |"
    labels = {"dis": "DIS, clean crop given", "mixed": "rectifier, one frame", "oracle": "rectifier, clean crop given"}
    head += "".join(f" {labels.get(r['config']['name'], r['config']['name'])}: EPE (/ zero) |" for r in runs)
    lines = [head, "|---|---:|---:|---:|" + "---:|" * len(runs)]
    for cat in ("structured", "mixed", "natural", "charts"):
        base = runs[0]["by_category"].get(cat)
        if base is None:
            continue
        floor = base["mean_px"] / base["epe_zero"]
        row = f"| {cat} | {base['crops']} ({base['images']}) | {base['epe_zero']:.3f} | "
        row += f"{base['mean_px']:.3f} ({floor:.2f}) |"
        for r in runs:
            c = r["by_category"][cat]
            row += f" {c['epe']:.3f} ({c['ratio']:.4f} ± {c['ratio_se']:.2g}) |"
        lines.append(row)
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", nargs="+", type=Path, help="print the markdown table of these result files, then exit")
    ap.add_argument("--name")
    ap.add_argument("--train", choices=["all", "structured", "natural"], default="all")
    ap.add_argument("--charts", type=float, default=1 / 3, help="share of synthetic charts in each training batch")
    ap.add_argument("--oracle", action="store_true", help="the rectifier also sees the clean image (6 channels)")
    ap.add_argument("--dis", action="store_true", help="no training: DIS optical flow given the clean image")
    ap.add_argument("--sizes", action="store_true", help="no training: the crop-mean share of the flow by crop size")
    ap.add_argument("--source", choices=["tilt", "turb"], default="tilt", help="the frame the rectifier sees")
    ap.add_argument("--patch", type=int, default=96)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--minutes", type=float, default=20.0, help="training budget, CPU minutes (evaluations excluded)")
    ap.add_argument("--max-iters", type=int, default=100_000)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--eval-crops", type=int, default=1000, help="held-out crops of photographs (spread over images)")
    ap.add_argument("--eval-charts", type=int, default=256)
    ap.add_argument("--max-side", type=int, default=512)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--cache", type=Path, default=None, help="folder for the decoded images and depth priors")
    ap.add_argument("--rows", action="store_true", help="keep every held-out crop's row in the JSON (≈ 0.25 MB)")
    args = ap.parse_args()
    config = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    if args.table:
        print(table(args.table))
        return
    if not args.name:
        ap.error("--name is required")
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    t0 = time.time()
    out = Path(args.out or ROOT / "benchmarks" / "results" / f"rectifier_tilt_{args.name}.json")

    folders = TRAIN["structured"] + TRAIN["natural"] if args.train == "all" else TRAIN[args.train]
    if args.sizes:
        result = {"config": config, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
        write_json(out, result | {"by_size": mean_share_by_size(args)})
        return
    if args.dis:
        eval_set = build_eval(args, synth_seed=12345)
        rows = evaluate(None, eval_set, args)
        result = {"config": config | {"method": "cv2.DISOpticalFlow MEDIUM, clean → tilted (grey)"}}
        if args.rows:
            result["rows"] = rows
        result["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        for key, f in (("category", "cat"), ("folder", "folder")):
            result[f"by_{key}"] = summarise(rows, lambda r, f=f: r[f])
        result["by_bin"] = summarise(rows, lambda r: ["weak", "medium", "strong"][r["bin"]])
        write_json(out, result)
        print(table([out]))
        return
    train_images = Images(folders, args.max_side, args.patch, args.cache)
    eval_set = build_eval(args, synth_seed=12345)
    setup_s = time.time() - t0
    print(f"setup {setup_s:.0f} s: {len(train_images.images)} train images, {sum(len(b['names']) for b in eval_set)} "
          "eval crops", flush=True)  # fmt: skip

    sims = [Simulator(p, "cpu") for p in geometry_bank("field", {})]
    synth = OnTheFlySynthesis(sims, bins=("weak", "medium", "strong"), seed=args.seed, use_depth=True)
    rng = np.random.default_rng(args.seed)
    net = TiltRectifier(1, injection="none", widths=WIDTHS, in_channels=6 if args.oracle else 3)
    params = sum(p.numel() for p in net.parameters())
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    n_charts = int(round(args.charts * args.batch))
    curve, it, train_s = [], 0, 0.0
    budget_s = args.minutes * 60
    # an estimate of the total for the cosine schedule, corrected once the speed is known
    total = args.max_iters
    while it < total:
        ts = time.process_time()  # CPU time: the machine is shared, so wall time says little
        clean, _ = train_images.crops(rng, args.batch - n_charts, args.patch, flip=True)
        if n_charts:
            ch = charts(rng, n_charts, args.patch)
            clean = {k: torch.cat([clean[k], ch[k]]) for k in clean}
        b = synth(clean)
        x = model_input(b, args.oracle, args.source)
        pred = net(x, torch.zeros(x.shape[0], 1, *x.shape[-2:]))
        loss = (pred - b["bwd_flow_px"]).abs().mean()  # L_flow (Eq. 12)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        it += 1
        train_s += time.process_time() - ts
        if it == 50:  # plan the cosine schedule from the measured speed
            total = min(args.max_iters, int(budget_s / (train_s / it)))
        lr = 1e-6 + 0.5 * (args.lr - 1e-6) * (1 + math.cos(math.pi * min(it, total) / total))  # cosine to 1e-6
        for g in opt.param_groups:
            g["lr"] = lr
        if it % 50 == 0:
            print(f"it {it}/{total} loss {loss.item():.4f} lr {lr:.2e} {train_s:.0f} s", flush=True)
        if it % args.eval_every == 0 or it == total:
            rows = evaluate(net, eval_set, args)
            summ = summarise(rows, lambda r: r["cat"])
            curve.append({"iter": it, "train_cpu_s": round(train_s, 1), "loss": float(loss), "by_category": summ})
            write_json(out.with_name(out.stem + "_curve.json"), {"config": config, "curve": curve})
            print(json.dumps({"iter": it, **{k: round(v["ratio"], 4) for k, v in summ.items()}}), flush=True)
    rows = evaluate(net, eval_set, args)
    result = {
        "config": config | {"widths": WIDTHS, "parameters": params, "train_folders": folders},
        "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__, "threads": 1},
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "iterations": it,
        "crops_seen": it * args.batch,
        "train_cpu_s": round(train_s, 1),
        "wall_s": round(time.time() - t0, 1),
        "setup_s": round(setup_s, 1),
        "structure_thresholds_widths": [NATURAL_WIDTHS, STRUCTURED_WIDTHS],
        "by_category": summarise(rows, lambda r: r["cat"]),
        "by_folder": summarise(rows, lambda r: r["folder"]),
        "by_bin": summarise(rows, lambda r: ["weak", "medium", "strong"][r["bin"]]),
        "curve": curve,
    }
    if args.rows:
        result["rows"] = rows
    write_json(out, result)
    out.with_name(out.stem + "_curve.json").unlink(missing_ok=True)
    print(json.dumps({k: result[k] for k in ("iterations", "train_cpu_s", "by_category")}, indent=1))


if __name__ == "__main__":
    main()
