# issue 36: fit the interval's widening beyond the gain table's box from the calibration clips of cal36.py
# (docs/measure.md, "Beyond the calibrated box"; strength.LARGE_TILT_LOG_SD). Per clip e = ln(estimate / truth); its
# variance is modelled as the interval's own (tiles, clip term, texture, small footprint) plus a²·u_tilt² + b²·u_wide²,
# with u_tilt = ln(tilt rms / 2.98 px) above the calibrated box's largest tilt (D/r0 4.5 at λ/(D·ifov) = 2 px) and
# u_wide = ln(footprint / 38.1 px) above the table's largest footprint (0 inside); a², b² by non-negative least squares
# of e² − s² on u². There e is one-sided (the estimate errs high), so the code widens the lower bound only, by a; b came
# out 0 and has no term in the code: python3 fit36.py cal36.jsonl
import json
import math
import sys

import numpy as np
from scipy.optimize import nnls

TILT_BOX_PX = math.sqrt(0.1816) * 2.0 * 4.5 ** (5 / 6)
WIDE_BOX_PX = 38.1
rows = [json.loads(line) for line in open(sys.argv[1])]
rows = [r for r in rows if "error" not in r]
e2, s2, u = [], [], []
for r in rows:
    e = math.log(r["est"] / r["dr0"])
    s = r["log_sd"]
    ut = math.log(max(r["tilt_rms_px"] / TILT_BOX_PX, 1.0))
    uw = math.log(max(r["footprint_px"] / WIDE_BOX_PX, 1.0))
    # the interval's own variance at the point (the widening terms of the code under calibration excluded)
    own = sum(v * v for k, v in s.items() if k not in ("large_tilt_lower", "footprint_below"))
    own += (0.3 * math.log(max(4.0 / r["footprint_px"], 1.0))) ** 2  # EXTRAPOLATION_LOG_SD below the table
    e2.append(e * e)
    s2.append(own)
    u.append((ut * ut, uw * uw))
e2, s2, u = np.array(e2), np.array(s2), np.array(u)
coef, _ = nnls(u, e2 - s2)
a, b = np.sqrt(coef)
n_tilt, n_wide = int((u[:, 0] > 0).sum()), int((u[:, 1] > 0).sum())
print(f"clips {len(rows)}, beyond the tilt box {n_tilt}, beyond the footprint box {n_wide}")
print(f"LARGE_TILT_LOG_SD = {a:.3f}, WIDE_FOOTPRINT_LOG_SD = {b:.3f}")
for name, mask in (("inside", (u.sum(1) == 0)), ("tilt", u[:, 0] > 0), ("wide", u[:, 1] > 0)):
    if mask.any():
        z = np.sqrt(e2[mask] / (s2[mask] + u[mask] @ coef))
        before = np.mean(np.sqrt(e2[mask] / s2[mask]) <= 1.655)
        print(f"{name}: n={mask.sum()}, covered at z=1.655 before {before:.2f}, after {np.mean(z <= 1.655):.2f}")
