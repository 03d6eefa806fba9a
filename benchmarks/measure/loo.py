# The interval's clip term: candidate models compared on the calibration clips only (loo.json from fitgain.py: each
# clip measured with the gain model refitted without it). A model gives the variance of ln(D̂/D) that the tile
# bootstrap does not see, v = β·f(clip), fitted by least squares of e² − s_tiles² on its features f (e = ln(D̂/D)).
# Each is judged by a second leave-one-out: clip i's v from the model fitted on the other clips, its interval
# ln D̂ ± z·sqrt(s_tiles² + v); coverage of the truth (all, per strength, per scene group) and the mean Gaussian
# negative log-likelihood of e. The validation clips are not read here.
#   python3 loo.py [loo.json]
import json
import sys

import numpy as np
from scipy import stats

rows = json.load(open(sys.argv[1] if len(sys.argv) > 1 else "loo.json"))
e = np.array([np.log(r["dr0_hat"] / r["dr0"]) for r in rows])
s = np.array([r["boot_sd"] for r in rows])
x = np.array([r["dr0_hat"] for r in rows])  # the estimate: what the interval is evaluated at
truth = np.array([r["dr0"] for r in rows])
outdoor = np.array([r["clip"].startswith("calo") for r in rows])
lowtex = np.array([r["clip"].startswith("calt") for r in rows])  # the fourth calibration: least textured crops
sub = {k: np.array([r["sub"][k] for r in rows]) for k in rows[0]["sub"]}
d_comp = np.log(sub["comp0"] / sub["comp1"])
d_orient = np.log(sub["orient0"] / sub["orient1"])
d_sep = np.log(sub["sep16"] / sub["sep64"])
valid = np.array([r["valid_fraction"] for r in rows])
small = np.log(38.1 / np.array([r["footprint_px"] for r in rows]))  # 0 at the default optics, 2.2 at 4.2 px
one = np.ones_like(x)
print(f"{len(rows)} calibration clips ({outdoor.sum()} outdoor, {lowtex.sum()} low texture); ln(D̂/D) rms "
      f"{np.sqrt(np.mean(e**2)):.4f}")  # fmt: skip
for name, v in (("bsds500", ~outdoor & ~lowtex), ("outdoor", outdoor), ("low tex", lowtex)):
    for X in sorted(set(truth)):
        sel = v & (truth == X)
        rms_e, rms_s = np.sqrt(np.mean(e[sel] ** 2)), np.sqrt(np.mean(s[sel] ** 2))
        print(f"  {name:8s} D/r0 {X}: n {sel.sum():2d}  mean {e[sel].mean():+.4f}  rms {rms_e:.4f}  boot {rms_s:.4f}")
for name, d in (("x/y component", d_comp), ("along x/along y", d_orient), ("16/64 px", d_sep)):
    c_abs, c_sgn = np.corrcoef(abs(d), abs(e))[0, 1], np.corrcoef(d, e)[0, 1]
    print(
        f"  disagreement {name}: rms {np.sqrt(np.mean(d**2)):.4f}, corr(|d|, |e|) {c_abs:+.2f}, corr(d, e) {c_sgn:+.2f}"
    )
print(f"  corr(|e|, 1/valid) {np.corrcoef(abs(e), 1 / valid)[0, 1]:+.2f}, corr(e, ln valid) "
      f"{np.corrcoef(e, np.log(valid))[0, 1]:+.2f}")  # fmt: skip

MODELS = {
    "constant": [one],
    "strength (a + b·D/r0)": [one, x],
    "strength + x/y component disagreement²": [one, x, d_comp**2],
    "strength + along-x/along-y disagreement²": [one, x, d_orient**2],
    "strength + 16/64 px disagreement²": [one, x, d_sep**2],
    "strength + all three disagreements²": [one, x, d_comp**2, d_orient**2, d_sep**2],
    "strength + 1/usable area": [one, x, 1 / valid],
    "strength + noise floor (D/r0)^(-10/3)": [one, x, x ** (-10 / 3)],
    "strength + ln(38/footprint)": [one, x, small],
    "strength + D/r0·ln(38/footprint)": [one, x, x * small],
}


def fit(F, sel):
    beta, *_ = np.linalg.lstsq(F[sel], (e**2 - s**2)[sel], rcond=None)
    return beta


def judge(F, z_fn):
    n = len(e)
    var = np.empty(n)
    for i in range(n):
        sel = np.arange(n) != i
        var[i] = max(float(F[i] @ fit(F, sel)), 0.0)
    sd = np.sqrt(s**2 + var)
    z = z_fn(n - 1 - F.shape[1])
    cov = np.abs(e) <= z * sd
    nll = np.mean(0.5 * np.log(2 * np.pi * sd**2) + e**2 / (2 * sd**2))
    return cov, nll, sd


print()
print("| model | z | coverage all | bsds500 | outdoor | low texture | 1.5 | 2.5 | 3.5 | 4.5 | mean NLL | median sd |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|")
for name, feats in MODELS.items():
    F = np.stack(feats, 1)
    for zname, z_fn in (("1.645", lambda dof: stats.norm.ppf(0.95)), ("t(n−p)", lambda dof: stats.t.ppf(0.95, dof))):
        cov, nll, sd = judge(F, z_fn)
        per = [f"{100 * cov[truth == X].mean():.0f} %" for X in sorted(set(truth))]
        groups = [
            f"{100 * cov[g].mean():.0f} %" if g.any() else "–"
            for g in (np.ones_like(outdoor), ~outdoor & ~lowtex, outdoor, lowtex)
        ]
        print(f"| {name} | {zname} | " + " | ".join(groups + per) + f" | {nll:.3f} | {np.median(sd):.4f} |")
    beta = fit(F, np.ones(len(e), bool))
    print(f"|   fitted on all: β = {', '.join(f'{b:.6f}' for b in beta)} | | | | | | | | | | | |")
