"""Simulated files from image files: what ``d2turb simulate`` (per image: NAME_turb.png, NAME_tilt.png,
NAME_fwd_flow_px.npy, NAME_meta.json) and ``d2turb simulate-video`` (a clip: turb/NNNNNN.png, tilt/, fwd_flow_px/,
meta.json, turb.mp4) write. The commands and the page both run these.

Flows on disk (``NAME_fwd_flow_px.npy``, ``fwd_flow_px/NNNNNN.npy``): float32 (2, H, W), the forward displacement Δ
in px, x then y (``SimResult.fwd_flow_px``): turb/tilt(x) ≈ clean(x + Δ(x)) (docs/flow.md). Earlier versions named
them ``NAME_flow.npy`` and ``flow/NNNNNN.npy``."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import re
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from d2turb.defaults import BATCH_PIXELS, DEFAULT_BATCH, DEFAULT_DEPTH, DEFAULT_DEVICE
from d2turb.depth import check_depth_spec, depth_for_image
from d2turb.device import resolve_device
from d2turb.errors import D2TurbError
from d2turb.io import (
    FileJob,
    check_output_dir,
    check_unique_stems,
    expand_inputs,
    list_images,
    read_image,
    to_uint8,
    write_image,
    write_json,
    write_npy,
)
from d2turb.io.jobs import JobOptions  # the options of every file job
from d2turb.sim import Simulator, TurbulenceParams, dr0_bin, sample_dr0
from d2turb.sim.sequence import check_sequence_args, wind_speeds
from d2turb.sim.tilt import path_nodes
from d2turb.video import VIDEO_HINT, Mp4Writer, can_write_mp4, is_video, iter_video


def batches(items, batch: int):
    """Group (path, dr0, image, depth) items of the same image size into lists of at most ``batch`` images
    and BATCH_PIXELS pixels, in input order per size; at most ~2 batches of images wait in memory."""
    pending: dict[tuple[int, int], list] = {}
    for item in items:
        size = tuple(item[2].shape[-2:])
        group = pending.setdefault(size, [])
        group.append(item)
        if len(group) >= max(1, min(batch, BATCH_PIXELS // (size[0] * size[1]))):
            yield pending.pop(size)
        elif sum(len(g) for g in pending.values()) > 2 * batch:
            yield pending.pop(next(iter(pending)))  # the oldest size
    yield from pending.values()


def _write_outputs(out: Path, name: str, turb, tilt, fwd_flow_px, meta: dict, png_level: int) -> None:
    write_image(out / f"{name}_turb.png", turb, png_level)
    if tilt is not None:
        write_image(out / f"{name}_tilt.png", tilt, png_level)
    if fwd_flow_px is not None:
        write_npy(out / f"{name}_fwd_flow_px.npy", fwd_flow_px.numpy().astype("float32"))
    write_json(out / f"{name}_meta.json", meta)


@dataclasses.dataclass(frozen=True)
class SimulateOptions(JobOptions):
    """The options of :func:`simulate_files` (``d2turb simulate``), besides :class:`~d2turb.io.JobOptions`' device,
    save_flow (NAME_fwd_flow_px.npy, float32 (2, H, W): the forward displacement Δ in px, x then y), png_level and
    fail_fast.

    Args:
        dr0_range: draw each image's D/r0 from this range (:func:`~d2turb.sim.sample_dr0`) instead of the params'.
        depth: a depth spec of :func:`d2turb.depth.depth_for_image`; ``disparity``: its maps hold disparity.
        seed: of the one generator of the whole job; batch: images simulated together (the result depends on both).
        save_tilt: write NAME_tilt.png.
    """

    dr0_range: tuple[float, float] | None = None
    depth: str = DEFAULT_DEPTH
    disparity: bool = False
    seed: int = 0
    batch: int = DEFAULT_BATCH
    save_tilt: bool = True


def simulate_files(
    inputs: list, out, params: TurbulenceParams, options: SimulateOptions | None = None, **kwargs
) -> int:
    """Simulate turbulence on image files into the folder ``out`` (``d2turb simulate``).

    Images of the same size are simulated in batches (the result depends on ``seed``, ``batch`` and the input
    list); outputs are written in the background. An unreadable input is reported in one ``error:`` line and
    skipped (``fail_fast``: raised).

    Args:
        inputs: image files and folders of images.
        out: the output folder.
        params: the simulator's parameters; their D/r0 unless ``dr0_range`` draws one per image.
        options, kwargs: the job's :class:`SimulateOptions`, or its fields as keywords (``seed=1``); a keyword
            given with ``options`` replaces that field of it.

    Returns:
        The exit status: 0 all done, 1 some inputs failed, 2 all failed.
    """
    o = SimulateOptions.of(options, **kwargs)
    depth, disparity, seed, batch, device = o.depth, o.disparity, o.seed, o.batch, o.device
    if batch < 1:
        raise D2TurbError(f"batch must be at least 1, got {batch}", param="batch")
    paths = expand_inputs(inputs)
    check_unique_stems(paths)
    check_depth_spec(depth)
    device = resolve_device(device)
    out = check_output_dir(out, inputs=paths)
    sim = Simulator(params, device=device)
    gen = torch.Generator().manual_seed(seed)
    if o.dr0_range is not None:
        strengths = sample_dr0(len(paths), *o.dr0_range, generator=gen).tolist()
    else:
        strengths = [params.dr0] * len(paths)
    job = FileJob("simulate", len(paths), o.fail_fast, max_pending=2 * batch, compute_device=device)

    def read(item: tuple) -> tuple:
        path, _ = item
        image = read_image(path)
        return image, depth_for_image(depth, path, image, is_disparity=disparity, device=device)

    items = job.each(zip(paths, strengths), read)  # the readable inputs: a bad one is reported and skipped
    readable = ((path, dr0, image, depth_map) for (path, dr0), (image, depth_map) in items)
    base_meta = params.to_dict()
    with job:
        for group in batches(readable, batch):
            job.before_compute()
            images = torch.stack([item[2] for item in group])
            depths = (
                None if group[0][3] is None else torch.stack([item[3].reshape(1, *images.shape[-2:]) for item in group])
            )
            dr0 = torch.tensor([item[1] for item in group], dtype=torch.float64)
            res = sim(images, depth=depths, dr0=dr0, generator=gen)
            turb = res.turb.float().cpu()
            tilt = res.tilt.float().cpu() if o.save_tilt else None
            fwd_flow_px = res.fwd_flow_px.float().cpu() if o.save_flow else None
            modulation = res.modulation.flatten(1).mean(1).tolist()
            for b, (path, value, image, _) in enumerate(group):
                meta = dict(
                    base_meta,
                    dr0=float(value),
                    r0_m=params.aperture_m / float(value),
                    bin=dr0_bin(value),
                    seed=seed,
                    batch=batch,
                    input=str(path),
                    depth=depth,
                    height=image.shape[1],
                    width=image.shape[2],
                    mean_modulation=float(modulation[b]),
                )
                job.submit(
                    _write_outputs,
                    out,
                    path.stem,
                    turb[b],
                    None if tilt is None else tilt[b],
                    None if fwd_flow_px is None else fwd_flow_px[b],
                    meta,
                    o.png_level,
                )
                print(f"{path.name}: D/r0 = {value:.3g} ({dr0_bin(value)}) -> {out / (path.stem + '_turb.png')}")
    return job.finish()


# ---- clips ---------------------------------------------------------------------------------------------------------
def _input_frames(path: Path, frames: int | None):
    """(iterator of (3,H,W) frames or a still tensor, number of frames or None, kind)."""
    if path.is_dir():
        files = list_images(path)
        if not files:
            raise D2TurbError(f"{path}: no images in the folder")
        files = files[:frames] if frames else files
        return (read_image(f) for f in files), len(files), "frames"
    if is_video(path):
        return (frame for _, frame in iter_video(path)), frames, "video"
    return read_image(path), frames or 64, "image"


def remove_stale_frames(out: Path, frames: int, kept: dict[str, bool]) -> None:
    """Frames an earlier run into ``out`` wrote beyond this run's ``frames`` (and all of those of a kind this run
    did not write), so that turb/, tilt/ and fwd_flow_px/ match meta.json (an earlier version's flow/ goes too).
    Only names of this job's pattern (six digits) are touched; a folder left empty is removed, and turb.mp4 when the
    earlier meta.json names it and this run wrote none."""
    kept = {**kept, "flow": False}  # the earlier versions' name of fwd_flow_px/
    for kind, suffix in (("turb", ".png"), ("tilt", ".png"), ("fwd_flow_px", ".npy"), ("flow", ".npy")):
        folder = out / kind
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            m = re.fullmatch(r"(\d{6})" + re.escape(suffix), p.name)
            if m and (not kept[kind] or int(m.group(1)) >= frames) and p.is_file():
                p.unlink()
        if not kept[kind] and not any(folder.iterdir()):
            folder.rmdir()
    if not kept["mp4"] and (out / "turb.mp4").is_file() and (out / "meta.json").is_file():
        try:
            earlier = json.loads((out / "meta.json").read_text())
        except (OSError, ValueError):
            earlier = None
        if isinstance(earlier, dict) and earlier.get("mp4") == "turb.mp4":
            (out / "turb.mp4").unlink()


def simulate_video(
    src,
    out,
    params: TurbulenceParams,
    *,
    frames: int | None = None,
    fps: float = 30.0,
    wind: float | list[float] = 1.0,
    wind_dir: float = 0.0,
    boil: float = 0.0,
    depth: str = DEFAULT_DEPTH,
    disparity: bool = False,
    seed: int = 0,
    save_tilt: bool = False,
    save_flow: bool = False,
    mp4: bool = True,
    device: str = DEFAULT_DEVICE,
) -> int:
    """A turbulent clip into the folder ``out`` (``d2turb simulate-video``): frozen-flow layers moved by the wind.

    Args:
        src: a still image (the scene stays, the air moves), a video file or a folder of frames (used frame by
            frame).
        out: the output folder: turb/NNNNNN.png per frame, meta.json, turb.mp4 (``mp4`` and the video extra),
            tilt/NNNNNN.png (``save_tilt``), fwd_flow_px/NNNNNN.npy (``save_flow``: float32 (2, H, W), the
            forward displacement Δ in px, x then y).
        frames: number of frames (default: 64 for an image, all frames of a video or folder).
        wind: transverse wind in m/s, or speeds from the aperture to the object interpolated along the path.
        wind_dir: drift direction in the image in degrees (0 = +x, 90 = +y); ``boil``: fraction of each layer's
            variance refreshed per frame.
        depth: a depth spec of :func:`d2turb.depth.depth_for_image` (of a video input: per frame).

    Returns:
        The exit status, 0.
    """
    src = Path(src)
    if not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    device = resolve_device(device)
    # the input's folder (for a folder of frames, that folder itself) may not be the output folder
    out = check_output_dir(out, inputs=[src] if src.is_file() else [src / "frame"])
    check_sequence_args(frames, fps, wind_dir, boil)
    t, _ = path_nodes(params.tilt_geometry, params.layer_z_frac, 12)
    speeds = wind_speeds(wind, t)
    source, n_frames, kind = _input_frames(src, frames)
    sim = Simulator(params, device=device)
    gen = torch.Generator().manual_seed(seed)
    mp4_path = _mp4_path(out, mp4)

    def depth_of(frame):
        d = depth_for_image(depth, src if kind == "image" else None, frame, disparity, device)
        return None if d is None else d[None]

    _announce_clip(src, out, source, n_frames, kind, depth, params.dr0)
    if kind == "image":
        image, depth_maps = source[None], depth_of(source)
    else:  # a moving input: depth (if any) per frame
        image, depth_maps = (f[None] for f in source), (None if depth == "none" else depth_of)
    seq = sim.sequence(
        image,
        frames=n_frames,
        fps=fps,
        wind=wind,
        wind_dir=wind_dir,
        boil=boil,
        depth=depth_maps,
        generator=gen,
    )
    frames_done = _write_clip_frames(seq, out, src, n_frames, save_tilt, save_flow, mp4_path, fps)
    written, size = frames_done["written"], frames_done["size"]
    kept = {"turb": True, "tilt": save_tilt, "fwd_flow_px": save_flow, "mp4": mp4_path is not None}
    try:
        remove_stale_frames(out, written, kept)
    except OSError as exc:
        raise D2TurbError(f"cannot remove the frames of an earlier run in {out}: {exc.strerror or exc}") from exc
    p = sim.params
    meta = p.to_dict()
    meta.update(
        input=str(src),
        input_kind=kind,
        frames=written,
        fps=fps,
        wind_m_s=wind,
        wind_dir_deg=wind_dir,
        boil=boil,
        layers=_layer_motion(p, t, speeds, fps),
        dr0=float(p.dr0),
        bin=dr0_bin(p.dr0),
        seed=seed,
        depth=depth,
        height=size[0],
        width=size[1],
        mean_modulation=float(np.mean(frames_done["mean_modulation"])),
        mp4=mp4_path.name if mp4_path is not None else None,
    )
    write_json(out / "meta.json", meta)
    # the wind's shift per frame of each layer's phase screen over the width of the beam there (meta.json: layers,
    # s_per_frame): consecutive frames decorrelate as it nears 1 (px_per_frame is the same shift at the object's
    # scale, huge for layers near the camera: not an image motion, so not printed)
    near = min(meta["layers"], key=lambda m: m["z_frac"])["s_per_frame"]  # the layers that weigh most in the tilt
    print(
        f"{src.name}: {written} frames of {size[1]}x{size[0]}, D/r0 = {p.dr0:.3g}; the wind moves the turbulence near "
        f"the camera {near:.2g} beam widths per frame (frame-to-frame tilt decorrelates as this nears 1; per layer: "
        f"meta.json) -> {out}" + (f" ({mp4_path.name})" if mp4_path else "")
    )
    return 0


def _mp4_path(out: Path, mp4: bool) -> Path | None:
    """out/turb.mp4 when asked for and PyAV can write it (else a note says why not)."""
    if not mp4:
        return None
    if can_write_mp4():
        return out / "turb.mp4"
    print(f"note: no mp4 written; {VIDEO_HINT}")
    return None


def _announce_clip(src: Path, out: Path, source, n_frames, kind: str, depth: str, dr0: float) -> None:
    """One line on stderr before the first (slow) frame: what is simulated and where it goes."""
    h, w = source.shape[-2:] if kind == "image" else (None, None)
    depth_text = "none" if depth == "none" else f"{depth}, " + ("once" if kind == "image" else "per frame")
    print(
        f"{src.name}: simulating {n_frames} frames"
        + (f" of {w}x{h}" if h else "")
        + f" at D/r0 = {dr0:.3g} (depth: {depth_text}); each frame is written to {out / 'turb'} as it is "
        "done, the bar's time estimate follows the first one",
        file=sys.stderr,
        flush=True,
    )


def _write_clip_frames(seq, out: Path, src: Path, n_frames, save_tilt, save_flow, mp4_path, fps) -> dict:
    """Each frame of ``seq`` (SimResults) to out/turb/, tilt/, fwd_flow_px/ and the mp4 as it comes; returns the
    number written, the frame size (H, W) and each frame's mean depth modulation. No frame at all is an error."""
    written, size, mean_mod = 0, None, []
    with contextlib.ExitStack() as stack:
        writer = None if mp4_path is None else stack.enter_context(Mp4Writer(mp4_path, fps))
        for i, res in enumerate(tqdm(seq, total=n_frames, unit="frame", desc=src.name)):
            write_image(out / "turb" / f"{i:06d}.png", res.turb[0])
            if save_tilt:
                write_image(out / "tilt" / f"{i:06d}.png", res.tilt[0])
            if save_flow:
                fwd_flow_px = res.fwd_flow_px[0].detach().cpu().numpy().astype(np.float32)
                write_npy(out / "fwd_flow_px" / f"{i:06d}.npy", fwd_flow_px)
            if writer is not None:
                writer.write(to_uint8(res.turb[0]))
            size = tuple(res.turb.shape[-2:])
            mean_mod.append(float(res.modulation.mean()))
            written += 1
        if written == 0:
            raise D2TurbError(f"{src}: no frames to simulate")
    return {"written": written, "size": size, "mean_modulation": mean_mod}


def _layer_motion(p: TurbulenceParams, z_frac, speeds, fps: float) -> list[dict]:
    """Per layer of the path: its place z/L, wind speed, and the wind's shift per frame in beam widths (s) and in
    px at the object's scale (meta.json's ``layers``)."""
    ifov_l = p.ifov_rad * p.path_length_m  # m per px at the object
    return [
        {
            "z_frac": float(z),
            "wind_m_s": float(v),
            "s_per_frame": float(v / fps / (p.aperture_m * (1 - z))),
            "px_per_frame": float(v / fps / (ifov_l * z)),
        }
        for z, v in zip(z_frac, speeds)
    ]
