# validation tables from validate.py's JSON lines: per geometry (default optics, "field" bank) and strength, bias,
# rms relative error, 90 % coverage and median interval width, plain and with the camera shake; the depth-modulated
# clips (--depth prior) listed against the D/r0 of their farthest point; the acceptance checks of issue 28.
#   python3 table.py val.jsonl [more.jsonl ...]
import json
import sys

import numpy as np

rows = [json.loads(line) for path in (sys.argv[1:] or ["val.jsonl"]) for line in open(path)]


def stats(cell, name, x):
    ok = [r for r in cell if "dr0" in r[name]]
    if not ok:
        return None
    rel = np.array([r[name]["dr0"] / x - 1 for r in ok])
    cov = np.mean([r[name]["dr0_ci"][0] <= x <= r[name]["dr0_ci"][1] for r in ok])
    width = np.median([(r[name]["dr0_ci"][1] - r[name]["dr0_ci"][0]) / x for r in ok])
    return {"n": len(ok), "bias": rel.mean(), "rms": np.sqrt(np.mean(rel**2)), "cov": cov, "width": width}


def pct(v, sign=False):
    return f"{100 * v:+.1f} %" if sign else f"{100 * v:.1f} %"


checks = []
print(
    "| geometry | D/r0 | clips (bsd100 / sunhays) | refused | measured | bias | rms rel. error | 90 % coverage "
    "| median CI width | with shake: bias | rms | coverage |"
)
print("|---|---|---|---|---|---|---|---|---|---|---|---|")
for geometry in ("default", "field"):
    for x in sorted({r["dr0_true"] for r in rows}):
        cell = [r for r in rows if r["geometry"] == geometry and r["depth"] == "none" and r["dr0_true"] == x]
        if not cell:
            continue
        p, s = stats(cell, "plain", x), stats(cell, "shake", x)
        scenes = f"{sum(r['scene'] == 'bsd100' for r in cell)} / {sum(r['scene'] == 'sunhays_outdoor' for r in cell)}"
        out = [geometry, f"{x:g}", f"{len(cell)} ({scenes})", str(len(cell) - (p["n"] if p else 0))]
        if p is None:
            print("| " + " | ".join(out + ["0"] + ["–"] * 7) + " |")
            continue
        out += [str(p["n"]), pct(p["bias"], True), pct(p["rms"]), f"{100 * p['cov']:.0f} %", pct(p["width"])]
        out += [pct(s["bias"], True), pct(s["rms"]), f"{100 * s['cov']:.0f} %"] if s else ["–"] * 3
        print("| " + " | ".join(out) + " |")
        checks.append(
            (
                f"{geometry} {x:g}",
                p["n"] >= 10,
                abs(p["bias"]) <= 0.10,
                p["rms"] <= 0.20,
                p["cov"] >= 0.80,
                s is not None
                and abs(s["bias"] - p["bias"]) <= 0.05
                and abs(s["rms"] - p["rms"]) <= 0.05
                and abs(s["cov"] - p["cov"]) <= 0.05,
            )
        )
print()
print("| cell | ≥ 10 measured | bias within ±10 % | rms ≤ 20 % | coverage ≥ 80 % | shake within 5 points |")
print("|---|---|---|---|---|---|")
for name, *ok in checks:
    print(f"| {name} | " + " | ".join("yes" if v else "**no**" for v in ok) + " |")

depth = [r for r in rows if r["depth"] != "none"]
if depth:
    print()
    print(
        "| depth-modulated clip | scene | D/r0 (farthest point) | measured D/r0 [90 %] | ratio | with shake | valid |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in sorted(depth, key=lambda r: (r["dr0_true"], r["clip"])):
        p, s = r["plain"], r["shake"]
        name = r["clip"].split("/")[-1]
        if "dr0" not in p:
            print(f"| {name} | {r['scene']} | {r['dr0_true']:g} | refused: {p['error'][:80]} | – | – | – |")
            continue
        sh = f"{s['dr0']:.2f}" if "dr0" in s else "refused"
        print(
            f"| {name} | {r['scene']} | {r['dr0_true']:g} | {p['dr0']:.2f} [{p['dr0_ci'][0]:.2f}, "
            f"{p['dr0_ci'][1]:.2f}] | {p['dr0'] / r['dr0_true']:.2f} | {sh} | {100 * p['valid_fraction']:.0f} % |"
        )
