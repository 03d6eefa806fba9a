"""Where the field clips' gain is lost (issue 49): oracle experiments on a ``make-dataset --profile field`` set,
scored as ``evaluate --clips`` scores (``d2turb.eval.clips``: each frame against its own truth, global offset removed,
8-px border left out, every ``stride``-th frame, window ``temporal``), each row against the input frame.

Rows per scored frame t (W(t) the restorer's window, ``window_start``):

* ``input``: the camera's frame t;
* ``ours mean`` / ``ours mean+blind`` / ``ours sharpest``: the restorer as ``evaluate --clips`` runs it (mean fusion,
  the blind deblur after it as the evaluation applies it; the sharpest fusion with no deblur);
* ``... @ECC``: the same output moved onto frame t's truth by its best rotation + translation (OpenCV ECC, Euclidean,
  started from the offset-removal's shift): what the output's pose (window mean, translation only) costs;
* ``... @meta``: the output moved from the window's mean TRUE pose (dx, dy, θ means) to frame t's true pose;
* ``O1 true reg``: every frame j of W(t) unwarped by its true turbulence flow (``bwd_flow_px``) and moved from its
  true pose to frame t's (rotation + translation, from the metadata), one cubic interpolation, averaged over the
  frames that see each pixel (frame t's own unwarped frame where none does); ``+blind`` (BlindDeblur as evaluated,
  given our restorer's first frame to observe) and ``+physics`` (the Wiener filter at the clip's true D/r0,
  ``physics_deblur_for``); ``O1 no-rot``: moved by the true translations only;
* ``ours mean+physics``: our mean fusion then the Wiener filter at the true D/r0; ``ours mean+blind(true tilt)``: the
  blind deblur given frame 0's TRUE observable turbulence flow to read (its flow less the window's mean) instead of
  our registered flow; ``... +input in boxes`` / ``+input in trail``: the input frame pasted inside frame t's boxes /
  inside the boxes of every frame of W(t) moved to frame t (a perfect moving-object fallback);
* ``turb unwarped``: frame t alone unwarped by its true flow (the input with its geometry fixed); ``tilt unwarped``: the
  dataset's tilt-only frame unwarped the same way (the flow's own accuracy, no blur, no camera);
* ``cam``: the truth through the clip's camera alone (no turbulence), replayed from its metadata
  (``data.field.camera_pipeline``'s steps on srgb_to_linear(gt) / exposure, the clip's noise seed); ``cam mean``: 16
  such frames moved to frame t by their true poses and averaged; ``cam mean+blind``; ``cam-<x>``: the camera without
  one of its stages (noise, sharpen, codec (and resize), optics blur), single frame and mean.

Each row is scored on the whole frame (``psnr``), outside the moving objects (``bg``: the boxes of every frame of
W(t) moved to frame t's pose, grown by 3 px, left out) and inside frame t's boxes (``box``, as ``box_psnr_aligned``).
The JSON holds per clip each row's means, the deblur records and the fallback's mean share inside the boxes and on the
background; per bin each row's gain over the input (mean ± s.e. over the clips) and the ``causes`` (``CAUSES``).
``--table {psnr,bg,box,causes,trail} JSON`` prints them as markdown.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python benchmarks/field_oracles.py val_field \
        --out benchmarks/results/field_oracles.json

docs/clips_field_oracles.md reads the output.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch

from d2turb.clip import ClipRestorer, window_start
from d2turb.clip.blind import BlindDeblur
from d2turb.data.field import coded
from d2turb.data.sequence import SequenceDataset
from d2turb.eval.clips import box_psnr, physics_deblur_for, remove_global_offset
from d2turb.sim.camera import linear_to_srgb, optics_blur, poisson_gaussian_noise, srgb_to_linear, unsharp_mask

BOX_GROW_PX = 3
CAMERA_ABLATIONS = ("noise", "sharpen", "codec", "blur")


# ---- geometry -------------------------------------------------------------------------------------------------------
def pose_of(shake: dict, t: int, rotation: bool = True) -> tuple[float, float, float]:
    return (shake["dx_px"][t], shake["dy_px"][t], shake["rot_deg"][t] if rotation else 0.0)


def pose_map(src_pose, dst_pose, size: int) -> tuple[np.ndarray, np.ndarray]:
    """2×3 A, b with src(y') = dst(y) for y' = A y + b: a world point p appears at R(θ)(p − c) + c + d in a frame."""
    c = (size - 1) / 2
    th = math.radians(src_pose[2] - dst_pose[2])
    a = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    b = -a @ np.array([c + dst_pose[0], c + dst_pose[1]]) + np.array([c + src_pose[0], c + src_pose[1]])
    return a, b


def moved(image: np.ndarray, src_pose, dst_pose, flow: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(H,W,3) float32 image of pose ``src_pose``, first unwarped by its backward flow (H,W,2) (``image(x + flow(x))``,
    its truth's geometry), then seen at ``dst_pose``; one cubic interpolation. Returns (image, valid (H,W) bool)."""
    h, w = image.shape[:2]
    a, b = pose_map(src_pose, dst_pose, h)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    zx = (a[0, 0] * xs + a[0, 1] * ys + b[0]).astype(np.float32)
    zy = (a[1, 0] * xs + a[1, 1] * ys + b[1]).astype(np.float32)
    valid = (zx >= 0) & (zx <= w - 1) & (zy >= 0) & (zy <= h - 1)
    if flow is not None:
        fx = cv2.remap(flow[..., 0], zx, zy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        fy = cv2.remap(flow[..., 1], zx, zy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        zx, zy = zx + fx, zy + fy
    out = cv2.remap(image, zx, zy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return out, valid


def window_mean(images, flows, poses, t: int, window: list[int], fallback: np.ndarray) -> np.ndarray:
    """Mean over the window of the frames moved to frame t's pose (each pixel over the frames that see it)."""
    acc = np.zeros_like(fallback)
    count = np.zeros(fallback.shape[:2], np.float32)
    for j in window:
        img, valid = moved(images[j], poses[j], poses[t], None if flows is None else flows[j])
        acc += img * valid[..., None]
        count += valid
    out = acc / np.maximum(count, 1)[..., None]
    none = count == 0
    out[none] = fallback[none]
    return out


def moved_box(box, src_pose, dst_pose, size: int) -> list[int]:
    """A box of a frame of ``src_pose`` as seen at ``dst_pose`` (bounding box of its corners, grown by BOX_GROW_PX)."""
    a, b = pose_map(dst_pose, src_pose, size)  # dst(y') = src(y) for y' = A y + b
    x0, y0, x1, y1 = box
    pts = np.array([[x, y] for x in (x0, x1) for y in (y0, y1)], np.float64)
    q = pts @ a.T + b
    g = BOX_GROW_PX
    return [math.floor(q[:, 0].min()) - g, math.floor(q[:, 1].min()) - g, math.ceil(q[:, 0].max()) + g,
            math.ceil(q[:, 1].max()) + g]  # fmt: skip


def ecc_aligned(image: np.ndarray, gt: np.ndarray, shift_yx) -> np.ndarray:
    """``image`` moved onto ``gt`` by its best Euclidean transform (ECC on the greys), started at ``shift_yx``."""
    grey = [cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY) for x in (gt, image)]
    m = np.array([[1, 0, -shift_yx[1]], [0, 1, -shift_yx[0]]], np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    try:
        _, m = cv2.findTransformECC(grey[0], grey[1], m, cv2.MOTION_EUCLIDEAN, criteria, None, 5)
    except cv2.error:
        return image
    return cv2.warpAffine(image, m, image.shape[1::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)  # fmt: skip


def share_stats(share: np.ndarray, boxes_t: list, trail: list) -> dict:
    """Mean moving-object fallback share inside frame t's boxes, and outside every box of the window (background)."""
    inside = np.zeros(share.shape, bool)
    for x0, y0, x1, y1 in boxes_t:
        inside[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = True
    bg = np.ones(share.shape, bool)
    for x0, y0, x1, y1 in trail:
        bg[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = False
    return {"boxes": float(share[inside].mean()) if inside.any() else 0.0, "background": float(share[bg].mean())}


def with_input(image: np.ndarray, frame: np.ndarray, boxes: list) -> np.ndarray:
    """``image`` with the input ``frame`` inside ``boxes`` (a perfect moving-object fallback)."""
    out = image.copy()
    h, w = out.shape[:2]
    for x0, y0, x1, y1 in boxes:
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        out[y0:y1, x0:x1] = frame[y0:y1, x0:x1]
    return out


# ---- the camera, replayed -------------------------------------------------------------------------------------------
def camera_replay(gt: torch.Tensor, cam: dict, noise_seed: int, fps: float, without: str | None = None) -> np.ndarray:
    """The truth frames (N,3,H,W) through the clip's camera alone (``data.field.camera_pipeline``'s stages on the
    linear scene srgb_to_linear(gt) / exposure), ``without`` one stage; (N,H,W,3) float32 in [0, 1]."""
    linear = srgb_to_linear(gt.float()) / cam["exposure"]
    gen = torch.Generator().manual_seed(int(noise_seed))
    x = linear if without == "blur" else optics_blur(linear, cam["defocus_px"], cam["mtf_sigma_px"])
    x = x.clamp_min(0) * cam["exposure"]
    if without != "noise":
        x = poisson_gaussian_noise(x, cam["shot_gain"], cam["read_sigma"], gen)
    x = linear_to_srgb(x.clamp(0, 1))
    if without != "sharpen":
        x = unsharp_mask(x, cam["sharpen_amount"], cam["sharpen_sigma_px"])
    u8 = np.clip(np.round(x.permute(0, 2, 3, 1).numpy() * 255), 0, 255).astype(np.uint8)
    if without != "codec":
        n, h, w = u8.shape[:3]
        if cam["resize_factor"] < 1:
            size = (max(2, round(w * cam["resize_factor"])), max(2, round(h * cam["resize_factor"])))
            small = coded(np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in u8]), cam, fps)
            u8 = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_CUBIC) for f in small])
        else:
            u8 = coded(u8, cam, fps)
    return u8.astype(np.float32) / 255


# ---- scoring --------------------------------------------------------------------------------------------------------
def to_hwc(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.permute(1, 2, 0).numpy().astype(np.float32))


def to_chw(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1).float()


def score(img: torch.Tensor, gt: torch.Tensor, boxes_t: list, bg_boxes: list) -> dict:
    """Offset-removed PSNR on the frame, outside ``bg_boxes`` and inside ``boxes_t`` (mean over boxes)."""
    img = img.clamp(0, 1)
    mv, ref, shift = remove_global_offset(img, gt)
    margin = (img.shape[-1] - mv.shape[-1]) // 2
    err = (mv.double() - ref.double()).pow(2).mean(0)
    out = {"psnr": float(10 * torch.log10(1 / err.mean().clamp_min(1e-10))), "shift": shift}
    mask = torch.ones_like(err, dtype=torch.bool)
    h, w = err.shape
    for x0, y0, x1, y1 in bg_boxes:
        mask[max(y0 - margin, 0) : max(min(y1 - margin, h), 0), max(x0 - margin, 0) : max(min(x1 - margin, w), 0)] = 0
    if mask.sum() > 0.2 * mask.numel():
        out["bg"] = float(10 * torch.log10(1 / err[mask].mean().clamp_min(1e-10)))
    vals = [box_psnr(mv, ref, b, margin) for b in boxes_t]
    vals = [v for v in vals if v is not None]
    if vals:
        out["box"] = float(np.mean(vals))
    return out


# ---- one clip -------------------------------------------------------------------------------------------------------
def restore(frames: torch.Tensor, temporal: int, fusion: str) -> list:
    return list(ClipRestorer(temporal=temporal, fusion=fusion).restore(frames))


def clip_rows(item: dict, record: dict, temporal: int, stride: int, fps: float) -> tuple[dict, dict]:
    turb, gt_all, n = item["turb"], item["gt"], item["turb"].shape[0]
    size = turb.shape[-1]
    field = record["field"]
    shake, cam = field["shake"], field["camera"]
    poses = [pose_of(shake, j) for j in range(n)]
    poses_tr = [pose_of(shake, j, rotation=False) for j in range(n)]
    boxes = [[b for b in item["boxes"][j].tolist() if b[0] >= 0] for j in range(n)]
    turb_np = [to_hwc(turb[j]) for j in range(n)]
    flows = [np.ascontiguousarray(item["bwd_flow_px"][j].permute(1, 2, 0).numpy().astype(np.float32)) for j in range(n)]

    ours = restore(turb, temporal, "mean")
    sharpest = restore(turb, temporal, "sharpest")
    blind, o1_blind, cam_blind, true_tilt_blind = (BlindDeblur(fusion="mean") for _ in range(4))
    for d in (blind, o1_blind, cam_blind):
        d.observe(ours[0])
    # the same deblur reading frame 0's TRUE observable turbulence motion (its flow less the window's mean flow)
    w0 = item["bwd_flow_px"][: min(temporal, n)].float()
    true_tilt_blind.observe(SimpleNamespace(bwd_flow_px=item["bwd_flow_px"][0].float() - w0.mean(0)))
    physics = physics_deblur_for(record, item["depth"], "mean")
    cams = {None: camera_replay(gt_all, cam, field["noise_seed"], fps)}
    for x in CAMERA_ABLATIONS:
        cams[x] = camera_replay(gt_all, cam, field["noise_seed"], fps, without=x)
    cams = {k: [np.ascontiguousarray(v[j]) for j in range(n)] for k, v in cams.items()}

    rows: dict[str, list[dict]] = {}
    fallback_share: list[dict] = []

    def add(name, image, t, bg):
        img = image if isinstance(image, torch.Tensor) else to_chw(image)
        rows.setdefault(name, []).append(score(img, gt_all[t], boxes[t], bg))

    for t in range(0, n, stride):
        window = list(range(window_start(t, temporal, n), min(window_start(t, temporal, n) + temporal, n)))
        bg = [moved_box(b, poses[j], poses[t], size) for j in window for b in boxes[j]]
        gt_t = gt_all[t]
        add("input", turb[t], t, bg)
        add("ours mean", ours[t].fused, t, bg)
        deblurred = blind(ours[t].fused)
        add("ours mean+blind", deblurred, t, bg)
        add("ours sharpest", sharpest[t].fused, t, bg)
        add("ours mean+physics", physics(ours[t].fused), t, bg)
        add("ours mean+blind(true tilt)", true_tilt_blind(ours[t].fused), t, bg)
        fallback_share.append(share_stats(ours[t].fallback.numpy(), boxes[t], bg))
        gt_np = to_hwc(gt_t)
        for name, img in (("ours mean+blind", deblurred), ("ours sharpest", sharpest[t].fused)):
            _, _, shift = remove_global_offset(img, gt_t)
            add(name + " @ECC", ecc_aligned(to_hwc(img), gt_np, shift), t, bg)
            mean_pose = tuple(np.mean([poses[j] for j in window], axis=0))
            add(name + " @meta", moved(to_hwc(img), mean_pose, poses[t])[0], t, bg)
        unwarped_t = moved(turb_np[t], poses[t], poses[t], flows[t])[0]
        add("turb unwarped", unwarped_t, t, bg)
        add("tilt unwarped", moved(to_hwc(item["tilt"][t]), poses[t], poses[t], flows[t])[0], t, bg)
        o1 = window_mean(turb_np, flows, poses, t, window, unwarped_t)
        add("O1 true reg", o1, t, bg)
        add("O1 true reg+blind", o1_blind(to_chw(o1)), t, bg)
        add("O1 true reg+physics", physics(to_chw(o1)), t, bg)
        add("O1 no-rot", window_mean(turb_np, flows, poses_tr, t, window, unwarped_t), t, bg)
        o1_blind_t = to_hwc(o1_blind(to_chw(o1)))
        for name, img in (("ours mean+blind", to_hwc(deblurred)), ("O1 true reg+blind", o1_blind_t)):
            add(name + " +input in boxes", with_input(img, turb_np[t], boxes[t]), t, bg)
            add(name + " +input in trail", with_input(img, turb_np[t], bg), t, bg)
        add("gt moved (check)", window_mean([to_hwc(g) for g in gt_all], None, poses, t, window, gt_np), t, bg)
        for key, frames in cams.items():
            tag = "cam" if key is None else f"cam-{key}"
            add(tag, frames[t], t, bg)
            mean = window_mean(frames, None, poses, t, window, frames[t])
            add(tag + " mean", mean, t, bg)
            if key is None:
                add("cam mean+blind", cam_blind(to_chw(mean)), t, bg)
    means = {}
    for name, scores in rows.items():
        means[name] = {k: float(np.mean([s[k] for s in scores if k in s])) for k in ("psnr", "bg", "box")
                       if any(k in s for s in scores)}  # fmt: skip
    gt_u8 = (gt_all * 255).round()
    info = {
        "saturated_frac": float((gt_u8 >= 255).any(1).float().mean()),
        "near_black_frac": float((gt_u8 <= 2).all(1).float().mean()),
        "blind_record": {k: v for k, v in (blind.record or {}).items() if isinstance(v, (int, float, str))},
        "cam_blind_record": {k: v for k, v in (cam_blind.record or {}).items() if isinstance(v, (int, float, str))},
        "true_tilt_blind_record": {
            k: v for k, v in (true_tilt_blind.record or {}).items() if isinstance(v, (int, float, str))
        },
        "fallback_share": {k: float(np.mean([f[k] for f in fallback_share])) for k in fallback_share[0]},
        "o1_blind_record": {k: v for k, v in (o1_blind.record or {}).items() if isinstance(v, (int, float, str))},
    }
    return means, info


def _mean_se(values: list[float]) -> tuple[float, float]:
    """Mean and its standard error (nan for a single value)."""
    se = float(np.std(values, ddof=1) / math.sqrt(len(values))) if len(values) > 1 else float("nan")
    return float(np.mean(values)), se


def summarise(samples: list[dict]) -> dict:
    """Per bin and row: mean ± standard error over the clips of the row's gain over the input (dB)."""
    out = {}
    for b in ("weak", "medium", "strong"):
        clips = [s for s in samples if s["bin"] == b]
        if not clips:
            continue
        out[b] = {}
        for row in clips[0]["rows"]:
            out[b][row] = {}
            for k in ("psnr", "bg", "box"):
                g = [c["rows"][row][k] - c["rows"]["input"][k] for c in clips if k in c["rows"][row]]
                a = [c["rows"][row][k] for c in clips if k in c["rows"][row]]
                if g:
                    mean, se = _mean_se(g)
                    out[b][row][k] = {"gain": mean, "se": se, "abs": float(np.mean(a)), "n": len(g)}
    return out


# (cause, (row, score) minus (row, score)): per-clip differences, gains over the input frame (dB)
CAUSES = (
    ("objects: background − whole-frame gain (default)", ("ours mean+blind", "bg"), ("ours mean+blind", "psnr")),
    ("objects: same with perfect registration + deblur", ("O1 true reg+blind", "bg"), ("O1 true reg+blind", "psnr")),
    ("registration: true − ours, both + physics (bg)", ("O1 true reg+physics", "bg"), ("ours mean+physics", "bg")),
    ("registration: true − ours, both + blind (bg)", ("O1 true reg+blind", "bg"), ("ours mean+blind", "bg")),
    ("registration: true − ours, no deblur (bg)", ("O1 true reg", "bg"), ("ours mean", "bg")),
    ("deblur: physics at true D/r0 − blind, on ours (bg)", ("ours mean+physics", "bg"), ("ours mean+blind", "bg")),
    ("deblur: physics@true D/r0 − blind (whole)", ("ours mean+physics", "psnr"), ("ours mean+blind", "psnr")),
    ("deblur: blind reading the true tilt − ours (whole)", ("ours mean+blind(true tilt)", "psnr"),
     ("ours mean+blind", "psnr")),
    ("deblur: what the blind deblur does to a turbulence-free mean (bg)", ("cam mean+blind", "bg"), ("cam mean", "bg")),
    ("output pose: ECC onto frame t's truth (whole)", ("ours mean+blind @ECC", "psnr"), ("ours mean+blind", "psnr")),
    ("rotation: true reg with − without rotation (bg)", ("O1 true reg", "bg"), ("O1 no-rot", "bg")),
    ("averaging: 16 truly registered frames − 1 unwarped frame (bg)", ("O1 true reg", "bg"), ("turb unwarped", "bg")),
    ("geometry: frame t unwarped by its true flow − input (bg)", ("turb unwarped", "bg"), ("input", "bg")),
    ("turbulence: camera-only frame − input (bg)", ("cam", "bg"), ("input", "bg")),
    ("camera: 16-frame mean − single camera-only frame (bg)", ("cam mean", "bg"), ("cam", "bg")),
    ("camera: noise in one frame (bg)", ("cam-noise", "bg"), ("cam", "bg")),
    ("camera: noise in the mean (bg)", ("cam-noise mean", "bg"), ("cam mean", "bg")),
    ("camera: codec + resize in the mean (bg)", ("cam-codec mean", "bg"), ("cam mean", "bg")),
    ("camera: optics blur in the mean (bg)", ("cam-blur mean", "bg"), ("cam mean", "bg")),
    ("camera: sharpening in the mean (bg)", ("cam-sharpen mean", "bg"), ("cam mean", "bg")),
)  # fmt: skip


def causes(samples: list[dict]) -> dict:
    """Per bin and cause: mean ± s.e. over the clips of the difference (dB)."""
    out = {}
    for b in ("weak", "medium", "strong"):
        clips = [s for s in samples if s["bin"] == b]
        if not clips:
            continue
        out[b] = {}
        for name, (ra, ka), (rb, kb) in CAUSES:
            d = [c["rows"][ra][ka] - c["rows"][rb][kb] for c in clips if ka in c["rows"][ra] and kb in c["rows"][rb]]
            if d:
                mean, se = _mean_se(d)
                out[b][name] = {"mean": mean, "se": se, "n": len(d)}
    return out


def causes_markdown(result: dict) -> str:
    c = result["causes"]
    bins = list(c)
    lines = ["| cause (dB) | " + " | ".join(bins) + " |", "|---|" + "---:|" * len(bins)]
    for name in c[bins[0]]:
        lines.append(
            f"| {name} | " + " | ".join(f"{c[b][name]['mean']:+.2f} ± {c[b][name]['se']:.2f}" for b in bins) + " |"
        )
    return "\n".join(lines) + "\n"


def trail_markdown(result: dict) -> str:
    """Per clip: the trail's share of the scored pixels (outside ``bg``) and of the squared error of the input and of
    the default, from the JSON's whole-frame and bg PSNRs and the dataset's boxes (``result["dataset"]``)."""
    lines = ["| clip | bin | trail pixels | input's error in it | default's error in it |", "|---|---|---:|---:|---:|"]
    recs = [json.loads(x) for x in (Path(result["dataset"]) / "meta.jsonl").read_text().splitlines() if x.strip()]
    by_id = {r["id"]: r for r in recs}
    size = int(json.loads((Path(result["dataset"]) / "dataset.json").read_text())["patch"])
    temporal, stride = result["settings"]["temporal"], result["settings"]["stride"]
    for s in result["samples"]:
        rec = by_id[s["id"]]
        n = len(rec["field"]["shake"]["dx_px"])
        poses = [pose_of(rec["field"]["shake"], j) for j in range(n)]
        fracs = []
        for t in range(0, n, stride):
            lo = window_start(t, temporal, n)
            keep = np.ones((size, size), bool)
            for j in range(lo, min(lo + temporal, n)):
                for obj in rec["field"]["objects"]:
                    if obj["boxes"][j] is not None:
                        x0, y0, x1, y1 = moved_box(obj["boxes"][j], poses[j], poses[t], size)
                        keep[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = False
            fracs.append(1 - keep[8:-8, 8:-8].mean())
        f = float(np.mean(fracs))
        shares = []
        for row in ("input", "ours mean+blind"):
            r = s["rows"][row]
            shares.append(1 - (1 - f) * 10 ** ((r["psnr"] - r["bg"]) / 10))
        lines.append(f"| {s['id']} | {s['bin']} | {f:.3f} | {shares[0]:.2f} | {shares[1]:.2f} |")
    return "\n".join(lines) + "\n"


def markdown(result: dict, key: str = "psnr") -> str:
    """Per bin: each row's gain over the input (mean ± s.e. over the bin's clips, dB) and its absolute score."""
    summary = result["summary"]
    bins = list(summary)
    lines = ["| row | " + " | ".join(f"{b} gain | {b} dB" for b in bins) + " |", "|---|" + "---:|" * (2 * len(bins))]
    for row in summary[bins[0]]:
        cells = []
        for b in bins:
            v = summary[b][row].get(key)
            cells.append("– | –" if v is None else f"{v['gain']:+.2f} ± {v['se']:.2f} | {v['abs']:.2f}")
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", help="the field dataset, or with --table a JSON this script wrote")
    ap.add_argument("--out")
    ap.add_argument(
        "--table", choices=("psnr", "bg", "box", "causes", "trail"), help="print the JSON's per-bin table of this score"
    )
    ap.add_argument("--temporal", type=int, default=16)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--max-clips", type=int, default=None)
    args = ap.parse_args()
    if args.table:
        result = json.loads(Path(args.root).read_text())
        tables = {"causes": causes_markdown, "trail": trail_markdown}
        print(tables.get(args.table, lambda r: markdown(r, args.table))(result), end="")
        return
    if not args.out:
        ap.error("--out is required")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    data = SequenceDataset(args.root)
    fps = float(json.loads((Path(args.root) / "dataset.json").read_text())["sequence"].get("fps", 30.0))
    samples = []
    n = len(data) if args.max_clips is None else min(args.max_clips, len(data))
    for idx in range(n):
        t0 = time.time()
        item, record = data[idx], data.records[idx]
        rows, info = clip_rows(item, record, args.temporal, args.stride, fps)
        cam, shake = record["field"]["camera"], record["field"]["shake"]
        samples.append(
            {
                "id": item["id"],
                "bin": record["bin"],
                "dr0": float(record["dr0"]),
                "camera": cam,
                "shake": {k: shake[k] for k in ("step_px", "rot_step_deg", "jump_rate", "jumps")},
                "rot_range_deg": float(np.ptp(shake["rot_deg"])),
                "objects": len(record["field"]["objects"]),
                **info,
                "rows": rows,
            }
        )
        r = rows
        print(
            f"{item['id']} {record['bin']:6s} in {r['input']['psnr']:.2f} ours {r['ours mean+blind']['psnr']:.2f} "
            f"O1 {r['O1 true reg']['psnr']:.2f} O1+b {r['O1 true reg+blind']['psnr']:.2f} cam {r['cam']['psnr']:.2f} "
            f"cam-mean {r['cam mean']['psnr']:.2f} ({time.time() - t0:.0f}s)",
            flush=True,
        )
    result = {
        "dataset": args.root,
        "settings": {"temporal": args.temporal, "stride": args.stride, "box_grow_px": BOX_GROW_PX},
        "summary": summarise(samples),
        "causes": causes(samples),
        "samples": samples,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(out)


if __name__ == "__main__":
    main()
