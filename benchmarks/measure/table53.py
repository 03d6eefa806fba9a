# issue 53 acceptance 1-3 from val53.py's rows (docs/measure.md, "Validation (issue 53)"): per measurement (nothing
# given: the seeing angle ρ; --ifov and --path-length given: D/r0, and ρ beside it) the clips counted (flat crops, a
# refusal with under 2 % textured area, left out), refused, the median |relative error| of the point estimate, the
# coverage of the 90 % interval with its binomial standard error sqrt(c(1 - c)/n) and its exact (Clopper-Pearson)
# one-sided 95 % lower bound (the standard error is 0 when every clip is covered), and the intervals' spans.
# python3 table53.py val53.jsonl [more.jsonl ...] (rows of one clip in several files are merged by label)
import json
import math
import re
import sys

import numpy as np
from scipy import stats as sps

rows: dict = {}
for path in sys.argv[1:]:
    for line in open(path):
        r = json.loads(line)
        rows.setdefault(r["i"], {}).update(r)


def flat(m: dict) -> bool:
    """A refusal for a crop with under 2 % textured area (acceptance 3: refused with the cause, not counted)."""
    e = m.get("error", "")
    t = re.search(r"only (\d+(?:\.\d+)?) % of the analysed area has texture ", e) or re.search(
        r"textured (\d+(?:\.\d+)?) %", e
    )
    return bool(t) and float(t.group(1)) < 2.0


def stats(label: str, key: str, truth: str) -> dict:
    ms = [(r[truth], r[label]) for r in rows.values() if label in r]
    counted = [(t, m) for t, m in ms if not flat(m)]
    est = [(t, m) for t, m in counted if "error" not in m]
    err = np.array([abs(m[key] / t - 1) for t, m in est])
    cov = np.array([m[f"{key}_ci"][0] <= t <= m[f"{key}_ci"][1] for t, m in est])
    span = np.array([m[f"{key}_ci"][1] / m[f"{key}_ci"][0] for _, m in est])
    n, c = len(est), float(cov.mean()) if len(est) else math.nan
    return {
        "clips": len(ms),
        "flat_refused": len(ms) - len(counted),
        "counted": len(counted),
        "refused": len(counted) - n,
        "refused_causes": [m["error"][:90] for _, m in counted if "error" in m],
        "estimated": n,
        "median_abs_rel_error": float(np.median(err)) if n else None,
        "coverage": c,
        "coverage_se": math.sqrt(c * (1 - c) / n) if n else None,
        "coverage_lower_95": float(sps.beta.ppf(0.05, int(cov.sum()), n - int(cov.sum()) + 1)) if n else None,
        "median_span": float(np.median(span)) if n else None,
        "span_range": [float(span.min()), float(span.max())] if n else None,
        "over_3x": int((span > 3).sum()),
        "missed": [
            (round(t, 3), round(m[key], 3), [round(v, 3) for v in m[f"{key}_ci"]])
            for (t, m), ok in zip(est, cov)
            if not ok
        ],
    }


out = {
    "nothing given: rho": stats("none", "seeing_px", "rho"),
    "ifov and path given: D/r0": stats("ifov_path", "dr0", "dr0"),
    "ifov and path given: rho": stats("ifov_path", "seeing_px", "rho"),
}
print(json.dumps(out, indent=1))
