"""Linear light in the clip restorer (issue 49, item 2), measured from outside ``d2turb.clip`` on field clips
(``make-dataset --profile field``: turbulence and the lens blur act on linear radiance, the camera sRGB-encodes,
sharpens and compresses; docs/clips_linear_light.md).

Per clip, four registration runs of :class:`~d2turb.clip.ClipRestorer` (window ``--temporal``, default options
otherwise) keep their fused frames of every ``--stride``-th output (cached): the sRGB frames with the mean fusion (the
default), the frames decoded to linear light (exact sRGB EOTF, ``sim.camera.srgb_to_linear``) with the mean fusion,
registered on their linear grey or (``registration_on_srgb``) on their sRGB grey, and the sRGB frames with the
sharpest fusion (``--deblur none``). The deblur variants are then applied to the cached fused frames exactly as
``ClipRestorer._deblurred`` does (the deblur, then ``clip.deblur.tone_guard(fused, out)`` unless
the deblur returned its input), each with its own :class:`~d2turb.clip.blind.BlindDeblur` (it decides on the first
fused frame it is given, frame 0, after ``observe`` of frame 0's registered flow, as in the restorer):

    a    default: mean fusion, BlindDeblur, tone guard (restore --temporal's default, clip_build.clip_restorer)
    a0   a without the tone guard (what ``evaluate --clips --deblur blind`` scores: it calls the deblur itself)
    a2   a with the tone guard in linear light: encode(tone_guard(decode(fused), decode(deblurred)))
    b    the deblur in linear light: LinearLightDeblur(BlindDeblur) (decode, deblur, encode), tone guard in sRGB
    b0   b without the tone guard
    b2   b with the tone guard in linear light (on the decoded fused frame and the linear deblur), then encoded
    b3   b2 with the linear guard's knee at 12/255 in sRGB terms (``KNEE_LINEAR_OF_SRGB``, 0.0037 linear) instead
         of 12/255 linear (0.24 encoded)
    b4   b2 with ``tone_guard_srgb_bands``: the guard's range and headroom in linear light, its near-black and
         near-white bands (12/255) on the encoded values, as today's
    b5   b4 with the blind decision on the sRGB frame (as a's), its filter and b4's guard in linear light
    b1   the blind decision on the sRGB frame (as a), its chosen filter applied in linear light, tone guard in sRGB
    c    the whole clip in linear light: registration, mean fusion, BlindDeblur and tone guard on linear frames,
         the output encoded
    c0   c without the tone guard
    c1   as c, the tone guard in sRGB (on the encoded fused and deblurred frames)
    c2   fusion in linear light, then the default sRGB deblur and tone guard on the encoded fused frame
    cf   fusion in linear light, no deblur (encoded)
    d    c with the registration on the sRGB greys (as a's: ``registration_on_srgb``), the warps, the mean fusion,
         BlindDeblur and tone guard in linear light, the output encoded
    d3   d with the linear guard's knee as b3's
    d4   d with b4's guard
    df   d's fusion, no deblur (encoded)
    p    the physics Wiener deblur at the clip's true D/r0 and optics (``evaluate --deblur physics``,
         ``eval.clips.physics_deblur_for``; an oracle) on a's fused frames, tone guard in sRGB
    p2   p in linear light, tone guard in linear light (as b2)
    fused   mean fusion in sRGB, no deblur
    none    sharpest fusion, no deblur (``--deblur none``)

Scores as ``evaluate --clips`` (eval/clips.py): each scored frame against its own truth, PSNR with the global
sub-pixel offset removed (``remove_global_offset``), and inside the moving objects' boxes; per clip the mean over its
scored frames (boxes: over every box of every scored frame); per bin the mean over clips ± its standard error, and
each variant's paired difference to ``a`` (mean ± standard error over the bin's clips), and the paired differences
of ``PAIRS`` per bin and over all clips; the near-black / near-white shares of the real-clips report.

    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/clip_linear_light.py val_field24 \\
        --cache scratch/cache24 --out benchmarks/results/clip_linear_light_val_field24.json

(run on a snapshot of a commit's src, ``PYTHONPATH=<snapshot>/src ... --code-commit <sha>``, while clip/ changes)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import platform
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch

import d2turb
from d2turb.clip import ClipRestorer, pipeline
from d2turb.clip.blind import BlindDeblur
from d2turb.clip.deblur import TONE_HEADROOM, TONE_KNEE, TONE_WINDOW_PX, tone_guard
from d2turb.data.sequence import SequenceDataset
from d2turb.defaults import DEFAULT_FUSION, FUSION_WITHOUT_DEBLUR
from d2turb.eval.artifacts import tail_fractions
from d2turb.eval.clips import box_psnr, physics_deblur_for, remove_global_offset
from d2turb.eval.metrics import psnr
from d2turb.sim.camera import linear_to_srgb, srgb_to_linear

try:  # where a frame's grey is taken (registration_on_srgb)
    from d2turb.clip import frames as _GRAY_MODULE
except ImportError:  # before the clip room's redesign (05f9d3a)
    _GRAY_MODULE = pipeline

BINS = ("weak", "medium", "strong")
# the linear-light tone guard with its knee at TONE_KNEE in sRGB terms (decoded: 0.0037 linear) instead of 12/255 linear
KNEE_LINEAR_OF_SRGB = float(srgb_to_linear(torch.tensor(TONE_KNEE)))
KNEE_SRGB = float(linear_to_srgb(torch.tensor(TONE_KNEE)))  # 0.240: the linear-light guard's knee in sRGB
VARIANTS = (
    "a",
    "a0",
    "a2",
    "a3",
    "b",
    "b0",
    "b2",
    "b1",
    "c",
    "c0",
    "c1",
    "c2",
    "cf",
    "d",
    "df",
    "p",
    "p2",
    "fused",
    "none",
)


def decode(encoded: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded frame in [0, 1] → linear light (the exact EOTF of IEC 61966-2-1)."""
    return srgb_to_linear(encoded.clamp(0, 1))


def encode(linear: torch.Tensor) -> torch.Tensor:
    """Linear light → sRGB-encoded, not clipped (a deblur's over- and undershoots stay visible to the tone guard:
    below 0 linearly, above 1 by the power)."""
    return linear_to_srgb(linear)


class LinearLightDeblur:
    """A deblur of sRGB-encoded frames run in linear light: decode, ``inner``, encode. Every other attribute
    (``observe``, ``record``, ``note``, ``describe``) is ``inner``'s, so ClipRestorer and restore.json see the
    BlindDeblur as before; where ``inner`` returns its input (nothing to deblur) so does this (the restorer then skips
    the tone guard, as for ``inner`` itself). With ``guard`` the tone guard runs here, in linear light, on the
    decoded fused frame and ``inner``'s output (variant b2: give the restorer ``tone_guard=False``).

    Shape: (3, H, W) → (3, H, W)."""

    def __init__(self, inner, guard: bool = False):
        self.inner, self.guard = inner, guard

    def __call__(self, fused: torch.Tensor) -> torch.Tensor:
        linear = decode(fused)
        out = self.inner(linear)
        if out is linear:
            return fused
        return encode(tone_guard(linear, out)) if self.guard else encode(out)

    def __getattr__(self, name):
        return getattr(self.inner, name)


class DecidedInSrgb:
    """The blind deblur decided on the sRGB frame (its estimate and ringing guard as today), its chosen filter
    applied in linear light."""

    def __init__(self, inner: BlindDeblur):
        self.inner = inner

    def __call__(self, fused: torch.Tensor) -> torch.Tensor:
        if self.inner.record is None:
            self.inner.decide(fused)
        if self.inner.deblur is None:
            return fused
        return encode(self.inner.deblur(decode(fused)))

    def __getattr__(self, name):
        return getattr(self.inner, name)


def tone_guard_srgb_bands(fused_linear: torch.Tensor, deblurred_linear: torch.Tensor) -> torch.Tensor:
    """``clip.deblur.tone_guard`` (8bd8b5c) in linear light with its shadows' and highlights' bands where they are
    in sRGB: the local range [lo, hi] and its headroom in linear values, but no pixel moved into (or deeper into) the
    bands within TONE_KNEE of black or white *of the encoded value*, and the change faded by the encoded fused
    value's distance to them (``tone_guard`` with its one knee in linear light puts the dark band's edge at 0.24
    encoded, or, knee 0.0037, the bright one at 0.998).

    Shape: (C, H, W) each, linear light in [0, 1]."""
    window, headroom, knee = TONE_WINDOW_PX, TONE_HEADROOM, TONE_KNEE
    kernel = np.ones((window, window), np.uint8)
    src = np.ascontiguousarray(fused_linear.float().permute(1, 2, 0).numpy())
    lo = cv2.erode(src, kernel, borderType=cv2.BORDER_REPLICATE).reshape(src.shape)
    hi = cv2.dilate(src, kernel, borderType=cv2.BORDER_REPLICATE).reshape(src.shape)
    floor, ceiling = lo * np.float32(1 - headroom), hi + np.float32(headroom) * (1 - hi)
    dark, bright = (float(srgb_to_linear(torch.tensor(v))) for v in (knee, 1 - knee))
    np.minimum(ceiling, np.maximum(src, np.float32(bright)), out=ceiling)
    np.maximum(floor, np.minimum(src, np.float32(dark)), out=floor)
    floor, ceiling = torch.from_numpy(floor).permute(2, 0, 1), torch.from_numpy(ceiling).permute(2, 0, 1)
    out = torch.minimum(torch.maximum(deblurred_linear.float(), floor), ceiling)
    f = fused_linear.float()
    enc = encode(f)
    weight = (torch.minimum(enc, 1 - enc) / knee).clamp(0, 1)
    return (f + (out - f) * weight).clamp(0, 1)


def guarded(deblur, fused: torch.Tensor, guard: bool = True, **guard_kw) -> torch.Tensor:
    """``ClipRestorer._deblur``: the deblur, then the tone guard unless the deblur returned its input."""
    out = deblur(fused)
    return tone_guard(fused, out, **guard_kw) if guard and out is not fused else out


def guarded_in_linear(deblur, fused: torch.Tensor, linear_deblur: bool, **guard_kw) -> torch.Tensor:
    """The tone guard in linear light around a deblur of the sRGB frame ``fused``: the deblur on the sRGB frame
    (``linear_deblur`` False) or on the decoded one (True), then ``tone_guard`` on the linear fused and deblurred
    frames, encoded."""
    lin = decode(fused)
    if linear_deblur:
        out = deblur(lin)
        return fused if out is lin else encode(tone_guard(lin, out, **guard_kw))
    out = deblur(fused)
    return fused if out is fused else encode(tone_guard(lin, srgb_to_linear(out), **guard_kw))


def _run(frames: torch.Tensor, temporal: int, fusion: str, stride: int) -> dict:
    """Fused frames of every ``stride``-th output and frame 0's registered flow (what BlindDeblur.observe keeps)."""
    kept, flow0 = {}, None
    for o in ClipRestorer(temporal=temporal, fusion=fusion).restore(frames):
        if flow0 is None:
            flow0 = o.bwd_flow_px.clone()
        if o.index % stride == 0:
            kept[o.index] = o.fused.clone()
    return {"index": list(kept), "fused": torch.stack(list(kept.values())), "flow0": flow0}


@contextlib.contextmanager
def registration_on_srgb():
    """While open, ClipRestorer's registration reads the sRGB grey of a linear-light frame: the one call of
    ``to_gray_u8`` on a colour frame (the frame's ``gray`` as it is taken in: ``clip.frames.HeldFrame.of`` since the
    clip room's redesign, ``pipeline._stream`` before; the camera placement and every round's DIS read it, the rounds'
    references are means of those greys, one channel, left as they are) gets the frame encoded first. A benchmark's
    patch of the module's name, undone on exit: the warps and the fusion stay in linear light."""
    module = _GRAY_MODULE
    original = module.to_gray_u8

    def gray(frame_hwc: np.ndarray) -> np.ndarray:
        if frame_hwc.shape[2] == 3:
            frame_hwc = linear_to_srgb(torch.from_numpy(frame_hwc)).numpy()
        return original(frame_hwc)

    module.to_gray_u8 = gray
    try:
        yield
    finally:
        module.to_gray_u8 = original


def _runs(frames: torch.Tensor, temporal: int, stride: int) -> dict:
    """The registration runs of a clip, by name: each a thunk."""
    return {
        "srgb": lambda: _run(frames, temporal, DEFAULT_FUSION, stride),
        "linear": lambda: _run(decode(frames), temporal, DEFAULT_FUSION, stride),
        "sharpest": lambda: _run(frames, temporal, FUSION_WITHOUT_DEBLUR, stride),
        "linear_srgb_reg": lambda: _linear_srgb_reg(frames, temporal, stride),
    }


def _linear_srgb_reg(frames: torch.Tensor, temporal: int, stride: int) -> dict:
    with registration_on_srgb():
        return _run(decode(frames), temporal, DEFAULT_FUSION, stride)


def cache_clip(data: SequenceDataset, idx: int, cache: Path, temporal: int, stride: int) -> dict:
    """The clip's cached runs (those missing are computed and added)."""
    path = cache / f"clip_{temporal}_{stride}_{idx}.pt"
    item, rec = data[idx], data.records[idx]
    frames = item["turb"]
    if path.exists():
        c = torch.load(path)
    else:
        index = list(range(0, len(frames), stride))
        c = {
            "id": item["id"],
            "bin": rec["bin"],
            "dr0": float(rec["dr0"]),
            "index": index,
            "input": frames[index].clone(),
            "gt": item["gt"][index].clone(),
            "boxes": item["boxes"][index].clone() if "boxes" in item else None,
            "runs": {},
            "cpu_s": {},
        }
    missing = {k: v for k, v in _runs(frames, temporal, stride).items() if k not in c["runs"]}
    if not missing:
        return c
    for name, thunk in missing.items():
        t0 = time.process_time()
        c["runs"][name] = thunk()
        if not isinstance(c["cpu_s"], dict):  # caches of the first version: one figure for the first three runs
            c["cpu_s"] = {"first three runs": c["cpu_s"]}
        c["cpu_s"][name] = time.process_time() - t0
        assert c["runs"][name]["index"] == c["index"]
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(c, tmp)
    tmp.replace(path)
    return c


def _blind(flow0: torch.Tensor, wrap=None):
    b = BlindDeblur(fusion=DEFAULT_FUSION)
    d = b if wrap is None else wrap(b)
    d.observe(SimpleNamespace(bwd_flow_px=flow0))
    return d


def _linear_b4(deblur, fused: torch.Tensor) -> torch.Tensor:
    lin = decode(fused)
    out = deblur(lin)
    return fused if out is lin else encode(tone_guard_srgb_bands(lin, out))


def _decided_srgb_b5(deblur: BlindDeblur, fused: torch.Tensor) -> torch.Tensor:
    """b5: the blind decision on the sRGB frame (as a's), its filter and b4's guard in linear light."""
    if deblur.record is None:
        deblur.decide(fused)
    if deblur.deblur is None:
        return fused
    lin = decode(fused)
    return encode(tone_guard_srgb_bands(lin, deblur.deblur(lin)))


def _guard_d4(deblur, fused_linear: torch.Tensor) -> torch.Tensor:
    out = deblur(fused_linear)
    return encode(fused_linear if out is fused_linear else tone_guard_srgb_bands(fused_linear, out))


def variant_frames(c: dict, physics=None) -> tuple[dict[str, list[torch.Tensor]], dict]:
    """Each variant's output frames (sRGB) of one cached clip, and the blind decisions' descriptions; with
    ``physics`` (the clip's PhysicsDeblur at its true D/r0) also p and p2."""
    s, lin, sharp, hyb = (c["runs"][k] for k in ("srgb", "linear", "sharpest", "linear_srgb_reg"))
    fs, fl, fh = list(s["fused"]), list(lin["fused"]), list(hyb["fused"])
    deb = {
        "a": _blind(s["flow0"]),
        "a0": _blind(s["flow0"]),
        "a2": _blind(s["flow0"]),
        "a3": _blind(s["flow0"]),
        "b2": _blind(s["flow0"]),
        "c0": _blind(lin["flow0"]),
        "b": _blind(s["flow0"], LinearLightDeblur),
        "b0": _blind(s["flow0"], LinearLightDeblur),
        "b1": _blind(s["flow0"], DecidedInSrgb),
        "c": _blind(lin["flow0"]),
        "c1": _blind(lin["flow0"]),
        "c2": _blind(lin["flow0"]),
        "d": _blind(hyb["flow0"]),
        "d3": _blind(hyb["flow0"]),
        "d4": _blind(hyb["flow0"]),
        "b4": _blind(s["flow0"]),
        "b5": _blind(s["flow0"]),
        "b3": _blind(s["flow0"]),
    }
    out = {
        "input": list(c["input"]),
        "a": [guarded(deb["a"], f) for f in fs],
        "a0": [guarded(deb["a0"], f, guard=False) for f in fs],
        "a2": [guarded_in_linear(deb["a2"], f, linear_deblur=False) for f in fs],
        "a3": [guarded(deb["a3"], f, knee=KNEE_SRGB) for f in fs],
        "b": [guarded(deb["b"], f) for f in fs],
        "b0": [guarded(deb["b0"], f, guard=False) for f in fs],
        "b2": [guarded_in_linear(deb["b2"], f, linear_deblur=True) for f in fs],
        "b3": [guarded_in_linear(deb["b3"], f, linear_deblur=True, knee=KNEE_LINEAR_OF_SRGB) for f in fs],
        "b4": [_linear_b4(deb["b4"], f) for f in fs],
        "b5": [_decided_srgb_b5(deb["b5"], f) for f in fs],
        "b1": [guarded(deb["b1"], f) for f in fs],
        "c": [encode(guarded(deb["c"], f)) for f in fl],
        "c0": [encode(guarded(deb["c0"], f, guard=False)) for f in fl],
        "c1": [],
        "c2": [guarded(deb["c2"], encode(f)) for f in fl],
        "cf": [encode(f) for f in fl],
        "d": [encode(guarded(deb["d"], f)) for f in fh],
        "d3": [encode(guarded(deb["d3"], f, knee=KNEE_LINEAR_OF_SRGB)) for f in fh],
        "d4": [_guard_d4(deb["d4"], f) for f in fh],
        "df": [encode(f) for f in fh],
        "fused": fs,
        "none": list(sharp["fused"]),
    }
    if physics is not None:
        out["p"] = [guarded(physics, f) for f in fs]
        out["p2"] = [guarded_in_linear(physics, f, linear_deblur=True) for f in fs]
    for f in fl:
        d = deb["c1"](f)
        out["c1"].append(encode(f) if d is f else tone_guard(encode(f), encode(d)))
    notes = {k: d.describe() for k, d in deb.items()}
    return out, notes


def clip_scores(c: dict, frames: dict[str, list[torch.Tensor]]) -> dict[str, dict[str, float]]:
    """Per variant: psnr, psnr_aligned (frame means) and box_psnr_aligned (mean over boxes), as eval/clips.py; the
    near-black and near-white shares (%, luma ≤ 4/255, ≥ 251/255: ``eval.artifacts.tail_fractions``, the real-clips
    report's); ``truth``: the truth frames' shares."""
    scores = {}
    for name, imgs in frames.items():
        plain, aligned, boxes, tails = [], [], [], []
        for k, img in enumerate(imgs):
            img, gt = img.clamp(0, 1), c["gt"][k]
            tails.append(tail_fractions(img))
            moved, ref, _ = remove_global_offset(img, gt)
            plain.append(float(psnr(img[None], gt[None])))
            aligned.append(float(psnr(moved[None], ref[None])))
            if c["boxes"] is None:
                continue
            margin = (img.shape[-1] - moved.shape[-1]) // 2
            for box in c["boxes"][k].tolist():
                if box[0] < 0:
                    continue
                p, a = box_psnr(img, gt, box), box_psnr(moved, ref, box, margin)
                if p is not None and a is not None:
                    boxes.append(a)
        scores[name] = {
            "psnr": float(np.mean(plain)),
            "psnr_aligned": float(np.mean(aligned)),
            "box_psnr_aligned": float(np.mean(boxes)) if boxes else None,
            "near_black_pct": 100 * float(np.mean([t[0] for t in tails])),
            "near_white_pct": 100 * float(np.mean([t[1] for t in tails])),
        }
    tails = [tail_fractions(g) for g in c["gt"]]
    scores["truth"] = {
        "psnr": None,
        "psnr_aligned": None,
        "box_psnr_aligned": None,
        "near_black_pct": 100 * float(np.mean([t[0] for t in tails])),
        "near_white_pct": 100 * float(np.mean([t[1] for t in tails])),
    }
    return scores


def _mean_se(values: list[float]) -> dict:
    v = np.asarray([x for x in values if x is not None], np.float64)
    if not len(v):
        return {"mean": None, "se": None, "n": 0}
    se = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else None
    return {"mean": float(v.mean()), "se": se, "n": int(len(v))}


def summarise(samples: list[dict], names: list[str]) -> dict:
    table = {}
    for b in BINS:
        rows = [s for s in samples if s["bin"] == b]
        if not rows:
            continue
        table[b] = {}
        for key in ("psnr_aligned", "box_psnr_aligned", "psnr", "near_black_pct", "near_white_pct"):
            table[b][key] = {n: _mean_se([s["scores"][n][key] for s in rows]) for n in names}
            table[b][key + " minus a"] = {
                n: _mean_se(
                    [
                        s["scores"][n][key] - s["scores"]["a"][key]
                        for s in rows
                        if s["scores"][n].get(key) is not None and s["scores"]["a"][key] is not None
                    ]
                )
                for n in names
                if n != "a"
            }
    return table


# paired differences reported per bin and over all clips (x − y, mean ± standard error over clips)
PAIRS = (
    ("b2", "a"),
    ("b3", "a"),
    ("d3", "a"),
    ("b4", "a"),
    ("d4", "a"),
    ("b2", "b3"),
    ("b4", "b2"),
    ("b5", "a"),
    ("b5", "b4"),
    ("d4", "b4"),
    ("d", "a"),
    ("c", "a"),
    ("d", "b2"),
    ("c", "b2"),
    ("c", "d"),
    ("b", "a"),
    ("a", "a0"),
    ("p2", "p"),
    ("b4", "none"),
    ("b4", "input"),
    ("a", "input"),
    ("b2", "none"),
    ("d", "none"),
    ("a", "none"),
)


def pairs(samples: list[dict]) -> dict:
    """``"x − y"`` → key → bin (and ``all``) → mean ± standard error of the clips' paired differences."""
    out = {}
    for x, y in PAIRS:
        if x not in samples[0]["scores"] or y not in samples[0]["scores"]:
            continue
        out[f"{x} − {y}"] = {}
        for key in ("psnr_aligned", "box_psnr_aligned"):
            out[f"{x} − {y}"][key] = {}
            for b in (*BINS, "all"):
                rows = [s["scores"] for s in samples if b in ("all", s["bin"])]
                d = [r[x][key] - r[y][key] for r in rows if r[x][key] is not None and r[y][key] is not None]
                if d:  # with the clips more than 0.3 dB below y (issue 49's rule against --deblur none)
                    out[f"{x} − {y}"][key][b] = _mean_se(d) | {"below_0.3": int(sum(v < -0.3 for v in d))}
    return out


def pairs_markdown(p: dict) -> str:
    heads = " | ".join((*BINS, "all"))
    lines = [f"| paired difference, dB (clips > 0.3 below) | {heads} | boxes: {heads} |", "|---|" + "---:|" * 8]
    for name, keys in p.items():
        cells = [
            _pm(keys[k].get(b), "{:+.2f}") + (f" ({keys[k][b]['below_0.3']})" if b in keys[k] else "")
            for k in ("psnr_aligned", "box_psnr_aligned")
            for b in (*BINS, "all")
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pm(m: dict | None, fmt: str) -> str:
    if not m or m["mean"] is None:
        return "–"
    return fmt.format(m["mean"]) + ("" if m["se"] is None else f" ± {m['se']:.2f}")


def markdown(table: dict, names: list[str]) -> str:
    lines = []
    for key, title in (
        ("psnr_aligned", "offset-removed PSNR (dB)"),
        ("box_psnr_aligned", "inside the boxes"),
        ("near_black_pct", "near-black pixels (%)"),
        ("near_white_pct", "near-white pixels (%)"),
    ):
        if key not in table[next(iter(table))]:
            continue
        lines.append(f"| {title} | " + " | ".join(f"{b} | {b} − a" for b in table) + " |")
        lines.append("|---|" + "---:|---:|" * len(table))
        for n in names:
            cells = []
            for b in table:
                m = table[b][key][n]
                cells.append(_pm(m, "{:.2f}"))
                cells.append(_pm(table[b][key + " minus a"].get(n), "{:+.2f}") if n != "a" else "")
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def check_pipeline(data: SequenceDataset, idx: int, c: dict, frames: dict, temporal: int) -> dict:
    """The restorer itself with a, b and b2 as its deblur (its threaded deblur, observe, tone guard) against the
    variants computed from the cache: the largest absolute difference over the scored frames."""
    clip = data[idx]["turb"]
    out = {}
    for name, deblur, guard in (
        ("a", BlindDeblur(fusion=DEFAULT_FUSION), True),
        ("b", LinearLightDeblur(BlindDeblur()), True),
        ("b2", LinearLightDeblur(BlindDeblur(), guard=True), False),
    ):
        r = ClipRestorer(temporal=temporal, deblur=deblur, tone_guard=guard)
        got = {o.index: o.restored for o in r.restore(clip) if o.index in c["index"]}
        diff = max(float((got[i] - frames[name][k]).abs().max()) for k, i in enumerate(c["index"]))
        out[name] = {"max_abs_diff": diff, "record_kept": r.deblur.record is not None, "describe": r.deblur.describe()}
    return out


def _write(path: Path, result: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1, ensure_ascii=False))
    tmp.replace(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a make-dataset --profile field clip folder")
    ap.add_argument("--cache", type=Path, required=True, help="folder for the fused frames (outside the checkout)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--temporal", type=int, default=16)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--max-samples", type=int, default=None)
    ap.add_argument("--check-only", action="store_true", help="only the restorer-path check on the first clip")
    ap.add_argument("--resummarise", action="store_true", help="recompute the summaries of an existing --out JSON")
    ap.add_argument("--code-commit", default=None, help="the commit the imported d2turb is from (default: HEAD)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.resummarise:
        result = json.loads(args.out.read_text())
        names = list(result["samples"][0]["scores"])
        result["bins"], result["pairs"] = summarise(result["samples"], names), pairs(result["samples"])
        _write(args.out, result)
        print(markdown(result["bins"], names))
        print(pairs_markdown(result["pairs"]))
        return
    data = SequenceDataset(args.root)
    n = len(data) if args.max_samples is None else min(len(data), args.max_samples)
    samples, names, check = [], None, None
    if args.check_only:
        c = cache_clip(data, 0, args.cache, args.temporal, args.stride)
        print(json.dumps(check_pipeline(data, 0, c, variant_frames(c)[0], args.temporal), indent=1))
        return
    for idx in range(n):
        c = cache_clip(data, idx, args.cache, args.temporal, args.stride)
        frames, notes = variant_frames(c, physics_deblur_for(data.records[idx], data[idx]["depth"], DEFAULT_FUSION))
        names = [k for k in frames if k != "input"] + ["truth"]
        s = {"id": c["id"], "bin": c["bin"], "dr0": c["dr0"], "cpu_s_runs": c["cpu_s"], "blind": notes}
        # d's registration reads the sRGB greys: its flow should be a's (to the grey's rounding)
        flows = [c["runs"][k]["flow0"] for k in ("srgb", "linear_srgb_reg")]
        s["flow0_max_abs_diff_d_vs_a_px"] = float((flows[0] - flows[1]).abs().max())
        s["scores"] = clip_scores(c, frames)
        samples.append(s)
        if idx == 0:
            check = check_pipeline(data, idx, c, frames, args.temporal)
        print(
            c["id"],
            c["bin"],
            {k: round(v["psnr_aligned"], 2) for k, v in s["scores"].items() if v["psnr_aligned"]},
            flush=True,
        )
    names = ["input", *names]
    table = summarise(samples, names)
    commit = (
        args.code_commit or subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    )
    result = {
        "dataset": str(args.root),
        "settings": {"temporal": args.temporal, "stride": args.stride, "clips": n},
        "variants": __doc__.split("\n\n")[2],
        "commit": commit,
        "d2turb": str(Path(d2turb.__file__).parent),
        "machine": platform.platform(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "pipeline_check": check,
        "bins": table,
        "pairs": pairs(samples),
        "samples": samples,
    }
    _write(args.out, result)
    print(markdown(table, names))
    print(pairs_markdown(result["pairs"]))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
