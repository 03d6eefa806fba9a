"""Moving objects in a real 1080p clip (issue 35 item 4): the default clip restoration of ``dost_street_clip`` (cars
and a cyclist moving through a static street, camera shake) against the same run without the moving-object fallback.

    python benchmarks/fig_clip_moving.py [--clip ../shared/data/real/dost_street_clip] [--temporal 16]
        [--deblur auto|none|physics] [--fusion mean|sharpest|...]
        [--out docs/images/clip_moving_dost.jpg] [--json benchmarks/results/clip_moving_dost.json]

Both runs are ``d2turb restore CLIP --temporal 16`` (``d2turb.restore.clip_build.clip_restorer``, default options: two
registration rounds, mean fusion, the blind deblur; ``--deblur none``: the sharpest fusion, restore's default without a
deblur); the second sets ``ClipRestorer.fallback = False``. The regions
shown are found, not chosen: the largest connected areas where the default run used the single frame (fallback share
> 0.5) in the middle frame. Per region the figure shows input | without fallback | default | fallback share, and the
JSON holds each region's box, its share of single frame and the mean absolute difference of each output against the
input frame there (a ghost or a smear moves the output away from the frame; the static street is restored either
way). Skips (exit 0, a note) when the clip is absent.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_CLIP = HERE.parent.parent / "shared" / "data" / "real" / "dost_street_clip"
CROP_PX = 200  # side of each crop around a region's centre
ZOOM = 2


def restore(files: list[Path], temporal: int, fallback: bool, pick: int, **options) -> tuple[np.ndarray, np.ndarray]:
    """(restored frame ``pick`` (H,W,3) float32, its fallback share (H,W)) of the clip restoration with restore's
    defaults (``options``: ClipOptions fields, e.g. deblur, fusion)."""
    from d2turb.io import read_image
    from d2turb.restore.clip_build import clip_restorer

    restorer, _, _ = clip_restorer(files[0].parent, temporal, **options)
    restorer.fallback = fallback
    for out in restorer.restore(read_image(f) for f in files):
        if out.index == pick:
            return out.restored.permute(1, 2, 0).numpy().copy(), out.fallback.numpy().copy()
    raise RuntimeError("frame not restored")  # pragma: no cover


def regions(share: np.ndarray, count: int = 3) -> list[tuple[int, int, int, int, float]]:
    """The ``count`` largest connected areas of share > 0.5: (x, y, w, h, area px)."""
    n, _, stats, _ = cv2.connectedComponentsWithStats((share > 0.5).astype(np.uint8))
    boxes = sorted((stats[i] for i in range(1, n)), key=lambda s: -s[cv2.CC_STAT_AREA])[:count]
    return [(int(b[0]), int(b[1]), int(b[2]), int(b[3]), float(b[4])) for b in boxes]


def crop(image: np.ndarray, cx: int, cy: int) -> np.ndarray:
    h, w = image.shape[:2]
    x0 = min(max(0, cx - CROP_PX // 2), w - CROP_PX)
    y0 = min(max(0, cy - CROP_PX // 2), h - CROP_PX)
    return image[y0 : y0 + CROP_PX, x0 : x0 + CROP_PX]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default=str(DEFAULT_CLIP))
    ap.add_argument("--temporal", type=int, default=16)
    ap.add_argument("--deblur", default="auto", help="restore's --deblur (default auto)")
    ap.add_argument("--fusion", default=None, help="restore's --fusion (default: restore's for that deblur)")
    ap.add_argument("--out", default="clip_moving_dost.jpg")
    ap.add_argument("--json")
    args = ap.parse_args()
    clip = Path(args.clip)
    if not clip.is_dir():
        print(f"note: {clip} is absent (shared data): no figure", file=sys.stderr)
        return
    from d2turb.io import list_images, read_image

    files = list_images(clip)
    pick = len(files) // 2
    frame = read_image(files[pick]).permute(1, 2, 0).numpy()
    options = {"deblur": args.deblur, "fusion": args.fusion}
    default, share = restore(files, args.temporal, True, pick, **options)
    plain, _ = restore(files, args.temporal, False, pick, **options)
    rows, record = [], []
    for x, y, w, h, area in regions(share):
        cx, cy = x + w // 2, y + h // 2
        inside = (slice(y, y + h), slice(x, x + w))
        diff = {
            k: float(np.abs(v[inside] - frame[inside]).mean() * 255)
            for k, v in (("default", default), ("no_fallback", plain))
        }
        record.append(
            {
                "box_xywh": [x, y, w, h],
                "area_px": area,
                "mean_share": float(share[inside].mean()),
                "mean_abs_diff_to_input_grey_levels": diff,
            }
        )
        tiles = [
            crop(frame, cx, cy),
            crop(plain, cx, cy),
            crop(default, cx, cy),
            np.repeat(crop(share, cx, cy)[..., None], 3, axis=2),
        ]
        rows.append(
            np.concatenate(
                [cv2.resize(t, None, fx=ZOOM, fy=ZOOM, interpolation=cv2.INTER_NEAREST) for t in tiles], axis=1
            )
        )
    labels = ["input frame", "without fallback", "default (fallback)", "share of the single frame"]
    rows = [np.clip(r * 255 + 0.5, 0, 255).astype(np.uint8) for r in rows]
    head = np.full((36, rows[0].shape[1], 3), 255, np.uint8)
    for i, text in enumerate(labels):
        cv2.putText(head, text, (i * CROP_PX * ZOOM + 8, 26), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 2, cv2.LINE_AA)
    sheet = np.concatenate([head, *rows], axis=0)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 88])
    out = {
        "clip": clip.name,
        "frame": pick,
        "temporal": args.temporal,
        **options,
        "regions": record,
        "figure": args.out,
    }
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
