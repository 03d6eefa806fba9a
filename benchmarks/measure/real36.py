# issue 36: every multi-frame real clip, nothing given and a guess (docs/measure.md, "Real clips"):
# python3 real36.py > real36.jsonl
import json
from pathlib import Path

from d2turb.clip import strength as M
from d2turb.commands.measure import read_clip
from d2turb.errors import D2TurbError

R = Path("/work/shared/data/real")
clips = [R / "airport_heat_shimmer", R / "dost_street_clip", R / "otis_tmt_text_inputs", R / "dost_street_1080p"] + [
    R / "clear_hot_air" / f"test{i}.mp4" for i in range(1, 6)
]
for c in clips:
    try:
        frames = read_clip(c)
    except D2TurbError as e:
        print(json.dumps({"clip": c.name, "error": str(e)}), flush=True)
        continue
    for label, opt in (("none", None), ("guess", {"path_length_m": 1000.0, "ifov_rad": 525e-9 / 0.2})):
        try:
            r = M.measure_clip(frames, opt, window=30 if len(frames) >= 60 else None, bootstrap=100)
            lo, hi = r["dr0_ci"]
            print(
                json.dumps(
                    {
                        "clip": c.name,
                        "given": label,
                        "frames": len(frames),
                        "dr0": r["dr0"],
                        "ci": r["dr0_ci"],
                        "span": hi / lo if lo > 0 else None,
                        "refused": hi >= M.NEGLIGIBLE_DR0 and (not lo > 0 or hi / lo > M.MAX_SPAN),
                        "widened_by": r["widened_by"],
                        "valid": r["valid_fraction"],
                        "blur": r.get("blur"),
                        "q": r["lambda_over_d_px"],
                        "fp": r["fit"]["footprint_px"],
                        "windows": [(w["dr0"], w["dr0_ci"]) for w in r.get("windows", [])],
                    }
                ),
                flush=True,
            )
        except D2TurbError as e:
            print(json.dumps({"clip": c.name, "given": label, "error": str(e)}), flush=True)
