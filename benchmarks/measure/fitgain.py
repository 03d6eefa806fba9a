# Registration gain and the interval's clip term from the calibration statistics (calibrate.py → calib/*.npz).
# 1. Per clip and separation r, the gain ε = (DIS structure function) / (true-flow structure function), same pairs.
# 2. A smooth least-squares model of ln ε in ln r, ln footprint and D/r0 (quadratic, with interactions) over the
#    clips that measure_clip would accept (valid area ≥ MIN_VALID_FRACTION); printed as GAIN_TABLE.
# 3. Leave one clip out: refit the model without it, measure the clip with the predicted gains (the estimator of
#    d2turb.clip.strength on its DIS sums), compare ln(D̂/D) with the tile bootstrap's own spread. The clip term
#    CLIP_LOG_SD is the rms of ln(D̂/D) in quadrature minus the mean bootstrap variance.
# 4. The same leave-one-out estimate on windows of 16 and 32 frames of each clip (calibrate.py's window sums): the
#    clip term's growth for shorter windows, variance = a + b·D/r0 + c·(64/T − 1) (CLIP_WINDOW_VAR = c).
import glob
import json
import sys

import numpy as np
from scipy import stats

from d2turb.clip import motion
from d2turb.clip import strength as M
from d2turb.sim.tilt import dr0_from_tilt_variance

SEPS = (16, 32, 64)
FOOT, DR0 = (4.0, 8.0, 16.0, 38.1), (1.5, 2.5, 3.5, 4.5)


def features(r, f, x):
    lr, lf, xx = np.log(np.asarray(r) / 32.0), np.log(np.asarray(f) / 12.0), np.asarray(x) - 3.0
    return np.stack(
        np.broadcast_arrays(np.ones_like(lr * lf * xx), lr, lr**2, lf, lf**2, lr * lf, xx, xx * lf, xx * lr), -1
    )


clips = []
for path in sorted(glob.glob(sys.argv[1] if len(sys.argv) > 1 else "calib/*.npz")):
    z = np.load(path)
    info = json.loads(str(z["info"]))
    ser = [tuple(int(v) for v in s) for s in z["series"]]
    gain = {}
    for r in (8, 16, 32, 64):
        js = [j for j, s in enumerate(ser) if s[0] == r]
        dis = sum(z["num_dis"][:, j, 1:].sum() / z["pairs_dis"][:, j].sum() for j in js)
        true = sum(z["num_true"][:, j, 1:].sum() / z["pairs_true"][:, j].sum() for j in js)
        gain[r] = float(dis / true)
    info["footprint_px"] = info["aperture_m"] / (info["ifov_rad"] * info["path_length_m"])
    keep = [j for j, s in enumerate(ser) if s[0] in SEPS]
    clips.append(
        dict(info, gain=gain, num=z["num_dis"][:, keep], pairs=z["pairs_dis"][:, keep], series=[ser[j] for j in keep])
    )
    clips[-1]["true"] = (z["num_true"][:, keep], z["pairs_true"][:, keep])
    clips[-1]["windows"] = {
        int(k[len("num_dis_w") :]): [(n[:, keep], p[:, keep]) for n, p in zip(z[k], z["pairs" + k[3:]])]
        for k in z.files
        if k.startswith("num_dis_w")
    }
used = [c for c in clips if c["valid_fraction"] >= motion.MIN_VALID_FRACTION]
print(f"{len(clips)} calibration clips, {len(used)} with valid area ≥ {motion.MIN_VALID_FRACTION:.0%}")


def fit(cs):
    X = np.concatenate([features(SEPS, c["footprint_px"], c["dr0"]) for c in cs])
    y = np.concatenate([np.log([c["gain"][r] for r in SEPS]) for c in cs])
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return beta, y - X @ beta


beta, resid = fit(used)
print(f"gain model: rms residual of ln ε {np.sqrt(np.mean(resid**2)):.3f} over {resid.size} (clip, separation)")
table = np.exp(features(np.array(SEPS)[None, None], np.array(FOOT)[:, None, None], np.array(DR0)[None, :, None]) @ beta)
print("GAIN_FOOTPRINT_PX =", FOOT)
print("GAIN_TABLE = (  # [footprint][D/r0][separation 16, 32, 64 px]")
for row in table:
    print("    (" + ", ".join("(" + ", ".join(f"{v:.3f}" for v in cell) + ")" for cell in row) + "),")
print(")")


def measure(c, gains_fn, n_boot=200, seed=0):
    """D̂, the bootstrap sd of ln D̂ with the gains of gains_fn(dr0) (the estimator of estimate_from_sums), and the
    sub-estimates of the same clip from parts of its series with the same gains: x / y displacement component,
    separation along x / along y, each separation alone."""
    t_len = c["num"].shape[-1]
    unit = (c["wavelength_m"] / (c["aperture_m"] * c["ifov_rad"]),)  # λ/(D·ifov) px
    models = M.structure_models(c["series"], t_len, [c["ifov_rad"] * c["path_length_m"] / c["aperture_m"]])
    dr0 = 2.5
    for _ in range(3):
        gains = gains_fn(dr0)[None]
        sig2, _ = M.fit_nuisance(c["num"].sum(0), c["pairs"].sum(0), t_len, models, gains)
        dr0 = float(dr0_from_tilt_variance(sig2, *unit))
    sub = {}
    for key, idx in (("comp", 2), ("orient", 1), ("sep", 0)):
        for v in sorted({s[idx] for s in c["series"]}):
            sel = [j for j, s in enumerate(c["series"]) if s[idx] == v]
            s2, _ = M.fit_nuisance(
                c["num"][:, sel].sum(0), c["pairs"][:, sel].sum(0), t_len, models[..., sel, :], gains[:, sel]
            )
            sub[f"{key}{v}"] = float(dr0_from_tilt_variance(s2, *unit))
    rng = np.random.default_rng(seed)
    n = c["num"].shape[0]
    boot = []
    for _ in range(n_boot):
        pick = rng.integers(0, n, n)
        boot.append(M.fit_nuisance(c["num"][pick].sum(0), c["pairs"][pick].sum(0), t_len, models, gains)[0])
    if not boot:
        return dr0, 0.0, sub
    return dr0, float(np.std(np.log(dr0_from_tilt_variance(np.array(boot), *unit)))), sub


# the estimator on the simulator's true flow (no registration, ε = 1): the theory and the unseen-mean handling
true_err = []
for c in used:
    tc = dict(c, num=c["true"][0], pairs=c["true"][1])
    ones = np.ones(len(c["series"]))
    true_err.append((c["dr0"], measure(tc, lambda x, ones=ones: ones, n_boot=0)[0] / c["dr0"]))
for x in DR0:
    v = np.array([r for d, r in true_err if d == x])
    print(f"true flow, D/r0 {x}: D̂/D mean {v.mean():.3f}, min {v.min():.3f}, max {v.max():.3f} ({len(v)} clips)")

rows, loo, win_rows = [], [], []
for k, c in enumerate(used):
    b, _ = fit(used[:k] + used[k + 1 :])
    seps = np.array([s[0] for s in c["series"]])
    gains_fn = lambda x, b=b, seps=seps, f=c["footprint_px"]: np.exp(features(seps, f, x) @ b)  # noqa: E731
    dr0, sd, sub = measure(c, gains_fn)
    rows.append((c, np.log(dr0 / c["dr0"]), sd))
    win_rows.append((c["dr0"], 64, dr0, sd))
    for t_len, sums in sorted(c.get("windows", {}).items()):
        for num, pairs in sums:
            wd, wsd, _ = measure(dict(c, num=num, pairs=pairs), gains_fn)
            win_rows.append((c["dr0"], t_len, wd, wsd))
    loo.append({k: c[k] for k in ("clip", "image", "dr0", "footprint_px", "valid_fraction", "textured_fraction",
                                  "median_residual_grey")} | {"dr0_hat": dr0, "boot_sd": sd, "sub": sub})  # fmt: skip
    print(
        f"{c['clip']:14s} fp {c['footprint_px']:5.1f} valid {c['valid_fraction']:.2f} "
        f"res {c['median_residual_grey']:.2f}  D̂/D {dr0 / c['dr0']:.3f}  boot sd {sd:.3f}",
        flush=True,
    )
e = np.array([r[1] for r in rows])
s = np.array([r[2] for r in rows])
rms = lambda v: float(np.sqrt(np.mean(v**2)))  # noqa: E731
print(f"leave-one-out ln(D̂/D): mean {e.mean():+.4f}, rms {rms(e):.4f}, bootstrap sd rms {rms(s):.4f}")
for x in DR0:
    sel = np.array([r[0]["dr0"] == x for r in rows])
    print(f"  D/r0 {x}: n {sel.sum()}, mean {e[sel].mean():+.4f}, rms {rms(e[sel]):.4f}, boot {rms(s[sel]):.4f}")
for name in ("valid_fraction", "textured_fraction", "median_residual_grey", "footprint_px"):
    v = np.log([r[0][name] for r in rows])
    print(f"  corr(ln(D̂/D), ln {name}) = {np.corrcoef(e, v)[0, 1]:+.2f}")
clip = float(np.sqrt(max(np.mean(e**2) - np.mean(s**2), 0.0)))
print(f"pooled clip term {clip:.3f}  (ln D/r0; rms {rms(e):.3f} in quadrature minus the bootstrap's)")
# the clip variance against the strength: least squares of e² − s_tiles² on (1, D/r0), per clip
x = np.array([r[0]["dr0"] for r in rows])
coef, *_ = np.linalg.lstsq(np.stack([np.ones_like(x), x], 1), e**2 - s**2, rcond=None)
print("CLIP_LOG_SD =", tuple(round(float(np.sqrt(max(coef[0] + coef[1] * v, 0))), 3) for v in DR0), "(at GAIN_DR0)")
print(f"  variance = {coef[0]:.5f} + {coef[1]:.5f}·D/r0")
dof = len(rows) - 2  # two coefficients fitted on the clips: the interval's quantile is Student-t (Z90, CLIP_DOF)
print(f"CLIP_DOF = {dof}, Z90 = t_0.95({dof}) = {float(stats.t.ppf(0.95, dof))!r}")
# the clip term against the window length: every window of every clip, least squares of e² − s_tiles²
W = np.array([(d, t, np.log(h / d), sd) for d, t, h, sd in win_rows])
for t_len in sorted(set(W[:, 1])):
    sel = W[:, 1] == t_len
    print(f"  window {int(t_len)} frames: n {sel.sum()}, mean {W[sel, 2].mean():+.4f}, rms {rms(W[sel, 2]):.4f}, "
          f"boot {rms(W[sel, 3]):.4f}")  # fmt: skip
F = np.stack([np.ones(len(W)), W[:, 0], 64.0 / W[:, 1] - 1], 1)
cw, *_ = np.linalg.lstsq(F, W[:, 2] ** 2 - W[:, 3] ** 2, rcond=None)
print(f"window model: variance = {cw[0]:.5f} + {cw[1]:.5f}·D/r0 + {cw[2]:.5f}·(64/T − 1): CLIP_WINDOW_VAR {cw[2]:.5f}")
json.dump(loo, open("loo.json", "w"), indent=0)  # per clip: truth, leave-one-out estimate, sub-estimates (loo.py)
