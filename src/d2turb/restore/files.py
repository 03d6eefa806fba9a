"""Restored files from image files, videos and clips: what ``d2turb restore`` writes and ``d2turb restore --temporal``
(a clip restored across frames). The commands and the page both run these.

One naming rule (docs/cli.md, :func:`d2turb.restore.compare.output_name`): every output is named after its input,
``NAME_<what>.<ext>``, NAME being an image's or a video's file stem, or a folder clip's folder name:
``NAME_restored.png`` (an image, a frame: a video's frames are NAME_NNNNNN), ``NAME_restored.mp4`` (a video, a
clip), ``NAME_compare.png`` / ``NAME_compare.mp4`` (``--compare``), ``NAME_bwd_flow_px.npy`` (the backward flow V̂:
warp(NAME_deblurred, V̂) ≈ NAME_restored), ``NAME_deblurred.png``, ``NAME_fused.png``; a clip's flows are
``fwd_flow_px/NNNNNN.npy`` (forward: frame(x) ≈ restored(x + Δ(x))). Earlier versions named both ``flow``."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from PIL import Image, ImageOps
from tqdm import tqdm

from d2turb.clip import ClipRestorer, PhysicsDeblur
from d2turb.clip.blind import BlindDeblur
from d2turb.clip.strength import estimate_words, measure_clip, undetermined_dr0
from d2turb.defaults import DEFAULT_FUSION, FUSION_WITHOUT_DEBLUR
from d2turb.device import limit_malloc_arenas, resolve_device
from d2turb.errors import D2TurbError, FileErrors, summary
from d2turb.io import (
    BackgroundWriter,
    FileJob,
    SharedUint8,
    check_output_dir,
    check_unique_stems,
    expand_inputs,
    list_images,
    read_frame,
    read_image,
    write_image,
    write_json,
    write_npy,
)
from d2turb.io import named_error as _named  # an input's error, naming it
from d2turb.io.jobs import JobOptions  # the options of every file job
from d2turb.ops.splat import invert_flow
from d2turb.restore.compare import output_name, side_by_side
from d2turb.restore.single import Restorer
from d2turb.sim import Optics, TurbulenceParams
from d2turb.video import VIDEO_HINT, Mp4Writer, can_write_mp4, is_video, iter_video, video_fps, video_size


def split_inputs(inputs: list) -> tuple[list[Path], list[Path]]:
    """(image files, video files) of ``inputs`` (files and folders); output names must be unique."""
    images, videos = [], []
    for item in inputs:
        p = Path(item)
        if is_video(p):
            videos.append(p)
        else:
            images.extend(expand_inputs([item]))
    check_unique_stems(images + videos)
    return images, videos


def _save(out_dir: Path, stem: str, details: dict, save_flow: bool, save_intermediate: bool, png_level: int) -> None:
    write_image(out_dir / output_name(stem, "restored", "png"), details["restored"], png_level)
    if save_flow:
        write_npy(out_dir / output_name(stem, "bwd_flow_px", "npy"), details["bwd_flow_px"].numpy().astype(np.float32))
    if save_intermediate:
        write_image(out_dir / output_name(stem, "deblurred", "png"), details["deblurred"], png_level)


def _save_compare(out_dir: Path, name: str, before, after, png_level: int) -> None:
    """NAME_compare.png: input | restored, labelled."""
    write_image(out_dir / output_name(name, "compare", "png"), side_by_side([before, after]), png_level)


@contextlib.contextmanager
def _no_empty_out(out_dir: Path):
    """A run that leaves ``out_dir`` empty (it failed before writing anything, or wrote nothing) removes it, when it
    did not exist before the run: no empty output folder is left behind."""
    existed = out_dir.exists()
    try:
        yield
    finally:
        if not existed:
            with contextlib.suppress(OSError):
                out_dir.rmdir()  # only when empty


def _video_frames(path: Path) -> int | None:
    """Frame count stored in a video's container (None when it stores none or cannot be read: the bar counts up)."""
    try:
        return video_size(path)[0] or None
    except D2TurbError:
        return None


@dataclasses.dataclass(frozen=True)
class RestoreOptions(JobOptions):
    """The options of :func:`restore_files` (``d2turb restore``), besides :class:`~d2turb.io.JobOptions`'s device,
    save_flow, png_level and fail_fast.

    Args:
        tile, overlap: tiling of large images, px (a model's deblur).
        save_intermediate: also write NAME_deblurred.png (a clip's: FRAME_fused.png).
        compare: also write NAME_compare.png (input | restored, labelled) and for a video or clip NAME_compare.mp4.
    """

    tile: int = 512
    overlap: int = 64
    save_intermediate: bool = False
    compare: bool = False


@dataclasses.dataclass(frozen=True)
class ClipOptions(RestoreOptions):
    """The options of :func:`restore_clip_files` (``d2turb restore --temporal``) and :func:`clip_restorer`, besides
    :class:`RestoreOptions`'.

    Args:
        deblur, dr0, params: see :func:`clip_deblur`.
        passes, preset: registration rounds, DIS preset.
        fusion: fusion of the registered frames; None: the sharpest with ``deblur="none"``, the mean before a deblur
            (:attr:`fusion_used`).
        fps: frame rate of a folder clip's mp4 (None: 30).
    """

    deblur: str = "auto"
    dr0: float | None = None
    params: dict | None = None
    passes: int = 2
    preset: str = "fast"
    fusion: str | None = None
    fps: float | None = None

    @property
    def fusion_used(self) -> str:
        """The fusion the clip gets: ``fusion`` if given, else the sharpest without a deblur (the sharper frame) and the
        mean before one (the Wiener filter models the mean's blur; docs/clips.md)."""
        if self.fusion is not None:
            return self.fusion
        return FUSION_WITHOUT_DEBLUR if self.deblur == "none" else DEFAULT_FUSION


def restore_files(inputs: list, out, weights=None, options: RestoreOptions | None = None, **kwargs) -> int:
    """Restore images, folders of images and videos (frame by frame) with a model into the folder ``out``.

    Writes NAME_restored.png per image (a video's frames: NAME_NNNNNN_restored.png, and NAME_restored.mp4 with the
    video extra), NAME_bwd_flow_px.npy (``save_flow``: float32 (2, H, W), the predicted backward flow V̂ in px, x then
    y: warp(NAME_deblurred, V̂) ≈ NAME_restored)
    and NAME_deblurred.png (``save_intermediate``: Î_tilt); with ``compare``, NAME_compare.png (input | restored,
    labelled; a video's of its middle frame) and for a video NAME_compare.mp4 (side by side). An unreadable input
    is reported in one ``error:`` line and skipped (``fail_fast``: raised).

    Args:
        weights: as :class:`~d2turb.restore.Restorer` takes them (None: the recommended shipped model).
        options: :class:`RestoreOptions` (None: the defaults); ``kwargs``: any of its fields by name (``tile=256``),
            in place of the value in ``options``.

    Returns:
        The exit status: 0 all done, 1 some inputs failed, 2 all failed.
    """
    o = RestoreOptions.of(options, **kwargs)
    tile, overlap, device, compare, png_level = o.tile, o.overlap, o.device, o.compare, o.png_level
    images, videos = split_inputs(inputs)
    out_dir = check_output_dir(out, inputs=images + videos)
    restorer = Restorer(weights, device=resolve_device(device), tile=tile, overlap=overlap, progress=True)
    job = FileJob("restore", len(images) + len(videos), o.fail_fast, max_pending=4, compute_device=restorer.device)
    saved = (o.save_flow, o.save_intermediate, png_level)
    count = 0

    def restored(path: Path) -> tuple:
        image = read_image(path)
        job.before_compute()
        return image, restorer.restore_with_details(image)

    with _no_empty_out(out_dir), job:
        for path, (image, details) in job.each(images, restored, named=True, desc="restore", unit="img"):
            job.submit(_save, out_dir, path.stem, details, *saved)
            if compare:
                job.submit(_save_compare, out_dir, path.stem, image, details["restored"], png_level)
            count += 1
        for video in videos:
            total = _video_frames(video)
            bar = tqdm(iter_video(video), desc=video.name, unit="frame", total=total)
            frames = iter(bar)
            pick = (total or 0) // 2  # the frame of NAME_compare.png
            with contextlib.ExitStack() as stack:
                mp4 = side = None
                if can_write_mp4():  # the restored clip as a video too, at the input's frame rate
                    fps = video_fps(video)
                    mp4 = stack.enter_context(Mp4Writer(out_dir / output_name(video.stem, "restored", "mp4"), fps))
                    if compare:
                        side = stack.enter_context(Mp4Writer(out_dir / output_name(video.stem, "compare", "mp4"), fps))
                while True:
                    try:
                        i, frame = next(frames, (None, None))
                        if frame is None:
                            break
                        job.before_compute()
                        details = restorer.restore_with_details(frame)
                    except D2TurbError as exc:
                        bar.close()
                        job.record(exc, video)
                        break
                    job.submit(_save, out_dir, f"{video.stem}_{i:06d}", details, *saved)
                    if compare and i == pick:
                        job.submit(_save_compare, out_dir, video.stem, frame, details["restored"], png_level)
                    if mp4 is not None:
                        mp4.write(details["restored"])
                    if side is not None:
                        side.write(side_by_side([frame, details["restored"]]))
                    count += 1
                if mp4 is not None and not mp4.frames:
                    stack.pop_all()
                    mp4.abort()
                    if side is not None:
                        side.abort()
    print(f"restored {count} image(s) with {restorer.name} into {out_dir}")
    return job.finish()


# ---- clips ---------------------------------------------------------------------------------------------------------
def clip_frames(src: Path, errors, as_stored: bool = False) -> tuple[list[str], object]:
    """(frame names, iterator of (3,H,W) frames) of a clip; an unreadable frame of a folder is reported and
    skipped, a video that stops decoding ends the clip there (reported) through ``errors.record``. ``as_stored``:
    a folder's 8-bit frames as (H,W,3) uint8 arrays (:func:`~d2turb.io.read_frame`; ClipRestorer takes both)."""
    names: list[str] = []
    if is_video(src):

        def decoded():
            try:
                for i, frame in iter_video(src):
                    names.append(f"{src.stem}_{i:06d}")
                    yield frame
            except D2TurbError as exc:
                errors.record(_named(src, exc))

        return names, decoded()
    if not src.is_dir():
        raise D2TurbError(f"{src}: a clip is a video file or a folder of frames")
    files = list_images(src)
    if not files:
        raise D2TurbError(f"{src}: no images in the folder")

    def read():
        for f in files:
            try:
                frame = read_frame(f) if as_stored else read_image(f)
            except D2TurbError as exc:
                errors.record(_named(f, exc))
                continue
            names.append(f.stem)
            yield frame

    return names, read()


def _header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image as read_image will give it (EXIF rotation applied), from its header only;
    None when the header cannot be read (the restoring pass reports the file)."""
    try:
        with Image.open(path) as im:
            width, height = im.size
            if im.getexif().get(ImageOps.ExifTags.Base.Orientation) in (5, 6, 7, 8):
                width, height = height, width
            return width, height
    except Exception:  # noqa: BLE001 - any unreadable header: left to read_image, which reports it in one line
        return None


def check_frame_sizes(src: Path, files: list[Path]) -> None:
    """A folder clip's frames must have one size: checked from the headers before anything is measured or
    written, so that a mismatch is one error line and leaves nothing behind."""
    first = None
    for f in files:
        size = _header_size(f)
        if size is None:
            continue
        if first is None:
            first = (f, size)
        elif size != first[1]:
            raise D2TurbError(
                f"{src}: frame {f.name} is {size[0]}x{size[1]}, the first ({first[0].name}) is "
                f"{first[1][0]}x{first[1][1]}: all frames of a clip must have one size"
            )


def _kept(frames, store: dict):
    """The frames, each also kept in ``store`` under its index until the caller pops it."""
    for i, frame in enumerate(frames):
        store[i] = frame
        yield frame


MEASURE_FRAMES = 64  # frames from the clip's start used to measure D/r0 when it is not given


def _clip_head(src: Path) -> list:
    """The clip's first MEASURE_FRAMES readable frames (bad frames are reported once, by the restoring pass)."""
    _, frames = clip_frames(src, SimpleNamespace(record=lambda exc: None))
    return list(itertools.islice(frames, MEASURE_FRAMES))


def _turbulence_params(params: dict, **extra) -> TurbulenceParams:
    """TurbulenceParams from the given optics (the path length is the measurement's only); one-line error."""
    try:
        return TurbulenceParams(**{k: v for k, v in params.items() if k != "path_length_m"}, **extra)
    except TypeError as exc:
        raise D2TurbError(f"--param: {exc}") from exc


def _measured_dr0(head: list, params: dict) -> dict:
    """``d2turb measure``'s result on the clip's first frames ``head`` (the same estimates and intervals: what
    ``restore`` calls measured, ``measure`` measures); D2TurbError where measure refuses, or where D/r0 is not
    determined (the physics deblur needs it), said in measure's terms: the seeing angle without the camera."""
    optics = {k: params[k] for k in ("aperture_m", "wavelength_m", "ifov_rad", "path_length_m") if k in params}
    measured = measure_clip(head, optics, bootstrap=50)
    if not measured["dr0_determined"]:
        raise D2TurbError(undetermined_dr0(measured))
    return measured


def clip_deblur(
    choice: str, src: Path, *, dr0=None, params=None, device="cpu", tile=512, overlap=64, fusion=DEFAULT_FUSION
):
    """The deblur step of a clip: (None, a PhysicsDeblur, a BlindDeblur or a model's restore; its description; a
    record of the value used and where it came from, for the output folder's restore.json).

    Args:
        choice: ``none``; ``physics`` (Wiener with the turbulence OTF at ``dr0``, or at the D/r0 that
            ``d2turb measure`` finds on the clip's first MEASURE_FRAMES frames: refused where it is not determined);
            ``auto`` (physics at a given ``dr0``; else the blind deblur of :class:`~d2turb.clip.blind.BlindDeblur`,
            estimated on the fused frames of the one restoring pass: no second decode or registration); or a
            weights name/path.
        params: optics overrides (aperture_m, wavelength_m, ifov_rad, path_length_m).
        fusion: the clip's fusion; after ``sharpest`` the physics deblur models a weaker blur
            (:meth:`~d2turb.clip.PhysicsDeblur.for_fusion`) and the blind one keeps the Laplacian prior.
    """
    if choice == "none":
        return None, "none", {"method": "none"}
    params = dict(params or {})
    if choice == "auto" and dr0 is None:
        blind = BlindDeblur(fusion=fusion)
        return blind, blind.describe(), None  # the record comes from the deblur once it has seen a fused frame
    if choice in ("physics", "auto"):
        source, measured = "given (--dr0)", None
        optics = "given" if {"aperture_m", "wavelength_m", "ifov_rad"} & set(params) else "Nyquist (default)"
        if dr0 is None:
            head = _clip_head(src)
            try:
                measured = _measured_dr0(head, params)
            except D2TurbError as exc:
                raise D2TurbError(f"--deblur physics needs the turbulence strength: give --dr0 X ({exc})") from exc
            dr0 = measured["dr0"]
            source = (
                f"measured on the clip's first {len(head)} frames (d2turb measure, 90 %: {estimate_words(measured)})"
            )
            if "ifov_rad" not in params:  # the λ/(D·ifov) at which measure's estimate holds
                o = Optics(**{k: params[k] for k in ("aperture_m", "wavelength_m") if k in params})
                params["ifov_rad"] = o.wavelength_m / (o.aperture_m * measured["lambda_over_d_px"])
                optics = "λ/(D·ifov) of d2turb measure's estimate"
        p = _turbulence_params(params, dr0=min(dr0, 10.0))
        deblur = PhysicsDeblur.for_fusion(p.dr0, p.lambda_over_d_px, fusion)
        model = "" if deblur.dr0 == p.dr0 else f"; OTF at D/r0 {deblur.dr0:.3g} after the sharpest fusion"
        record = {
            "method": "physics",
            "dr0": p.dr0,
            "dr0_source": source,
            **({k: measured[k] for k in ("dr0_ci", "seeing_px", "seeing_px_ci")} if measured else {}),
            "otf_dr0": deblur.dr0,
            "lambda_over_d_px": p.lambda_over_d_px,
            "optics": optics,
            "balance": deblur.balance,
            "prior": deblur.prior,
        }
        return deblur, f"physics (D/r0 {p.dr0:.3g} {source}, λ/D {p.lambda_over_d_px:.3g} px{model})", record
    restorer = Restorer(choice, device=device, tile=tile, overlap=overlap)
    return restorer.restore, restorer.name, {"method": "model", "weights": restorer.name}


def clip_restorer(
    src, temporal: int, options: ClipOptions | None = None, **kwargs
) -> tuple[ClipRestorer, str, dict | None]:
    """The :class:`~d2turb.clip.ClipRestorer` of ``d2turb restore CLIP --temporal N`` with its deblur: the one place
    that builds it (``restore --temporal`` and ``evaluate --real-clips`` both call it, so their defaults agree).

    Args:
        src: the clip (a video file or a folder of frames; read here only when the physics deblur measures D/r0).
        temporal: frames per window.
        options: :class:`ClipOptions` (None: restore's defaults; ``kwargs``: its fields by name, in place of those);
            of them this reads deblur, dr0, params, device, tile, overlap (see :func:`clip_deblur`) and passes,
            preset, fusion (:attr:`ClipOptions.fusion_used`).

    Returns:
        (the restorer, its deblur already set; the deblur's description; its record for restore.json, None for the
        blind deblur until it has seen a fused frame: then ``restorer.deblur.record``).
    """
    o = ClipOptions.of(options, **kwargs)
    deblur, fusion = o.deblur, o.fusion_used
    restorer = ClipRestorer(temporal=temporal, passes=o.passes, fusion=fusion, preset=o.preset)
    restorer.deblur, name, record = clip_deblur(
        deblur, Path(src), dr0=o.dr0, params=o.params, device=o.device, tile=o.tile, overlap=o.overlap, fusion=fusion
    )
    return restorer, name, record


def restore_clip_files(src, out, temporal: int, options: ClipOptions | None = None, **kwargs) -> int:
    """Restore a clip across frames into the folder ``out`` (``d2turb restore --temporal``): registration to a
    sliding window of ``temporal`` frames, fusion, deblurring (:class:`~d2turb.clip.ClipRestorer`).

    NAME is the video's stem or the folder's name. Writes FRAME_restored.png per frame (a folder's frames keep
    their stems; a video's are NAME_NNNNNN), NAME_restored.mp4 (video extra), FRAME_fused.png
    (``save_intermediate``), fwd_flow_px/NNNNNN.npy (``save_flow``: float32 (2, H, W), the forward displacement Δ
    of each frame from the restored one, frame(x) ≈ restored(x + Δ(x)), px, x then y) and with ``compare``
    NAME_compare.mp4 (input | restored side by side, video extra) and NAME_compare.png (the middle frame).

    Args:
        src: a video file or a folder of frames.
        options: :class:`ClipOptions` (None: the defaults); ``kwargs``: its fields by name, in place of those
            (``dr0=2.0, compare=True``).

    Returns:
        The exit status: 0, or 1 when some frames could not be read (2 when none could).
    """
    o = ClipOptions.of(options, **kwargs)
    fps, passes, preset, fusion, png_level = o.fps, o.passes, o.preset, o.fusion_used, o.png_level
    src = Path(src)
    if not src.exists():
        raise D2TurbError(f"{src}: no such file or directory")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise D2TurbError(f"fps must be positive, got {fps}", param="fps")
    ClipRestorer(temporal=temporal, passes=passes, fusion=fusion, preset=preset)  # bad settings first, in one line
    files = list_images(src) if src.is_dir() else []
    check_frame_sizes(src, files)
    device = resolve_device(o.device)
    limit_malloc_arenas()  # before the threads of the stream start
    restorer, deblur_name, record = clip_restorer(src, temporal, dataclasses.replace(o, device=device))
    out_dir = check_output_dir(out, inputs=files or [src])
    errors = FileErrors(2, o.fail_fast)  # per frame: a bad one is reported and skipped
    names, frames = clip_frames(src, errors, as_stored=True)
    fps = video_fps(src) if is_video(src) else (fps or 30.0)
    total = _video_frames(src) if is_video(src) else len(files)  # the bar's total (unreadable frames aside)
    name = src.stem if is_video(src) else src.resolve().name
    mp4 = out_dir / output_name(name, "restored", "mp4")
    compare = o.compare
    side = out_dir / output_name(name, "compare", "mp4") if compare else None
    if not can_write_mp4():
        print(f"note: no mp4 written; {VIDEO_HINT}")
        mp4 = side = None
    inputs: dict[int, object] = {}  # with compare: the input frames not yet restored (bounded by the lookahead)
    if compare:
        frames = _kept(frames, inputs)
    pick, last = (total or 0) // 2, None  # NAME_compare.png: the middle frame (the last one, if fewer were read)
    print(
        f"restoring {src} over windows of {temporal} frames, fusion: {fusion}, deblur: {deblur_name}", file=sys.stderr
    )
    count = 0
    with _no_empty_out(out_dir), contextlib.ExitStack() as stack:
        # one writer thread, one frame queued: the PNGs keep pace (~0.1 s a 1080p frame) at 80 MB less peak than 2 + 2
        writer = stack.enter_context(BackgroundWriter(max_pending=1, compute_device=device, threads=1))
        video = None if mp4 is None else stack.enter_context(Mp4Writer(mp4, fps))
        side_video = None if side is None else stack.enter_context(Mp4Writer(side, fps))
        for frame in tqdm(restorer.restore(frames), desc=src.name, unit="frame", total=total or None):
            stem = names[frame.index]
            restored = SharedUint8(frame.restored)  # converted once, for the PNG and the mp4
            writer.submit(write_image, out_dir / output_name(stem, "restored", "png"), restored, png_level)
            if compare:
                before = inputs.pop(frame.index)
                if frame.index <= pick:
                    last = (before, frame.restored)
                if side_video is not None:
                    side_video.write(side_by_side([before, frame.restored]))
            if o.save_intermediate:
                writer.submit(write_image, out_dir / output_name(stem, "fused", "png"), frame.fused, png_level)
            if o.save_flow:  # forward displacement: frame(x) ≈ restored(x + Δ(x)), the inverse of bwd_flow_px
                fwd = invert_flow(frame.bwd_flow_px[None])[0].numpy().astype(np.float32)
                writer.submit(write_npy, out_dir / "fwd_flow_px" / f"{frame.index:06d}.npy", fwd)
            if video is not None:
                video.write(restored)
            count += 1
        if last is not None:
            writer.submit(_save_compare, out_dir, name, *last, png_level)
    if isinstance(restorer.deblur, BlindDeblur):
        record = restorer.deblur.record
        if restorer.deblur.note:
            print(
                f"note: {restorer.deblur.note}; for the physics deblur give --dr0 X (and the optics: --aperture, "
                "--wavelength, --ifov), or --deblur none",
                file=sys.stderr,
            )
    if count:  # a run that restored nothing leaves no folder (_no_empty_out), so no restore.json either
        settings = {"temporal": temporal, "passes": passes, "preset": preset, "fusion": fusion}
        write_json(out_dir / "restore.json", {"input": str(src), "frames": count, **settings, "deblur": record})
    print(f"restored {count} frame(s) of {src.name} into {out_dir}" + (f" ({mp4.name})" if mp4 else ""))
    if compare:
        print(f"before | after: {out_dir / output_name(name, 'compare', 'png')}" + (f", {side.name}" if side else ""))
    return summary("restore", count + len(errors.failed), len(errors.failed))
