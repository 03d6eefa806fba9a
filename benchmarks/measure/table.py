# validation table from val.jsonl: bias, rms relative error, 90 % coverage per strength, plain and with shake
import json
import sys

import numpy as np

rows = [json.loads(line) for line in open(sys.argv[1] if len(sys.argv) > 1 else "val.jsonl")]
print(
    "| D/r0 | clips | refused | bias | rms rel. error | 90 % coverage | median CI width "
    "| with shake: bias | rms | coverage |"
)
print("|---|---|---|---|---|---|---|---|---|---|")
for x in sorted({r["dr0_true"] for r in rows}):
    cell = [r for r in rows if r["dr0_true"] == x]
    out = [f"{x:g}", str(len(cell))]
    for k, name in enumerate(("plain", "shake")):
        ok = [r for r in cell if "dr0" in r[name]]
        if k == 0:
            out.append(str(len(cell) - len(ok)))
        if not ok:
            out += ["–"] * (4 if k == 0 else 3)
            continue
        rel = np.array([r[name]["dr0"] / x - 1 for r in ok])
        cov = np.mean([r[name]["dr0_ci"][0] <= x <= r[name]["dr0_ci"][1] for r in ok])
        width = np.median([(r[name]["dr0_ci"][1] - r[name]["dr0_ci"][0]) / x for r in ok])
        out += [f"{100 * rel.mean():+.1f} %", f"{100 * np.sqrt(np.mean(rel**2)):.1f} %", f"{100 * cov:.0f} %"]
        if k == 0:
            out.append(f"{100 * width:.0f} %")
    print("| " + " | ".join(out) + " |")
