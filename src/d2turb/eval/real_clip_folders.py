"""Which entries of a folder are clips, for the real clips report (``d2turb evaluate --real-clips DIR``;
:mod:`d2turb.eval.real_clips`).

A clip is a video file directly in DIR or in one of its sub-folders, or a sub-folder of at least
``MIN_CLIP_FRAMES`` image frames of one size (DIR itself too, when it holds such frames); anything else is listed
as not a clip, with the reason.
"""

from __future__ import annotations

import os
from pathlib import Path

from d2turb.errors import D2TurbError
from d2turb.io import list_images
from d2turb.restore.clip_source import check_frame_sizes
from d2turb.video import VIDEO_SUFFIXES, is_video, video_size

MIN_CLIP_FRAMES = 4  # a folder with fewer frames is not a clip (e.g. three frames 20 apart)


def _visible(entries) -> list[Path]:
    return sorted(p for p in entries if not p.name.startswith("."))


def _frames_clip(folder: Path) -> str | None:
    """None when ``folder``'s images make a clip, else the reason they do not."""
    files = list_images(folder)
    if len(files) < MIN_CLIP_FRAMES:
        return f"{len(files)} image(s): a clip needs at least {MIN_CLIP_FRAMES} frames"
    try:
        check_frame_sizes(folder, files)
    except D2TurbError as exc:
        return f"not one clip ({str(exc).split(': ', 1)[-1]})"
    return None


def find_clips(root: str | os.PathLike) -> tuple[dict[str, Path], list[dict]]:
    """The clips of ``root``: ({name: video file or folder of frames}, [{"path", "reason"} of what is not a clip]).

    Names are paths relative to ``root`` (a video without its suffix: ``clear_hot_air/test1``; ``root`` itself is
    ``.``). Raises ``D2TurbError`` when ``root`` is not a folder or holds no clip.
    """
    root = Path(root)
    if not root.is_dir():
        raise D2TurbError(f"{root}: not a directory (--real-clips takes a folder of clips)")
    clips: dict[str, Path] = {}
    not_clips: list[dict] = []
    entries = _visible(root.iterdir())
    if list_images(root):  # root's own frames
        reason = _frames_clip(root)
        if reason is None:
            clips["."] = root
        else:
            not_clips.append({"path": ".", "reason": reason})
    for entry in entries:
        rel = entry.relative_to(root).as_posix()
        if entry.is_file() and entry.suffix.lower() in VIDEO_SUFFIXES:
            clips[str(Path(rel).with_suffix(""))] = entry
        elif entry.is_dir():
            videos = [p for p in _visible(entry.iterdir()) if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES]
            for v in videos:
                clips[v.relative_to(root).with_suffix("").as_posix()] = v
            images = list_images(entry)
            if videos and images:
                not_clips.append({"path": rel, "reason": f"{len(images)} image(s) beside its videos (not a clip)"})
            elif not videos:
                reason = _frames_clip(entry)
                if reason is None:
                    clips[rel] = entry
                else:
                    not_clips.append({"path": rel, "reason": reason})
    if not clips:
        why = "; ".join(f"{n['path']}: {n['reason']}" for n in not_clips) or "it is empty"
        raise D2TurbError(f"{root}: no clips (a video file or a folder of {MIN_CLIP_FRAMES}+ frames); {why}")
    return clips, not_clips


def expected_frames(src: Path, max_frames: int) -> int | None:
    """Frames the run will read (bounded by ``max_frames``), None when a video's container does not say."""
    if is_video(src):
        try:
            stored = video_size(src)[0]
        except D2TurbError:
            return None
        return min(stored, max_frames) if stored else None
    return min(len(list_images(src)), max_frames)
