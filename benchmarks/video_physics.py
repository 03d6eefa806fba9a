"""Measured vs theoretical correlation of simulated turbulence in time and space (issue 14), the figure
docs/images/video_tilt.png and the animated clip docs/images/video_demo.gif. A statistics run: once, niced.

    nice -n 19 python3 benchmarks/video_physics.py --json benchmarks/results/video_physics.json

Theory: the path-integrated I0 ± I2 correlation (d2turb.sim.tilt, checked against the published integral
in tests/test_sim_lowfreq.py). Default geometry: D = 0.1 m, λ = 525 nm, L = 1 km, Nyquist pixels, D/r0 = 3.
Temporal: wind 1 m/s at 30 frames/s (s = v·Δt/D = 1/3 per frame at the aperture), one pixel of 2000
independent sequences × 65 frames (structure-function estimate, SE from 10 batch means), and the
correlation given the sequences' plane waves (``FrozenFlow.tilt_covariance``, mean of 200 sequences).
Spatial: the exact covariance of the still sampler and the plane-wave covariance of 40 sequences.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
import torch

from d2turb.io import write_json
from d2turb.sim import Simulator, TurbulenceParams
from d2turb.sim.sequence import FrozenFlow
from d2turb.sim.tilt import layer_tilt_correlation, path_nodes, tilt_correlation

LAGS = [1, 2, 4, 8, 16, 32, 64]
SEPARATIONS = [1, 8, 32, 64, 128, 192, 255, 320, 384, 448, 511]


def temporal_theory(lags, wind: float, fps: float, d: float) -> tuple[np.ndarray, np.ndarray]:
    t, w = path_nodes("path")
    s = np.asarray(lags, dtype=np.float64)[:, None] * wind / fps / (d * (1 - t))
    perp, par = layer_tilt_correlation(s)
    return perp @ w, par @ w


def temporal(params, wind, fps, n_seq=2000, n_frames=65, seed=0) -> dict:
    sim = Simulator(params)
    gen = torch.Generator().manual_seed(seed)
    state = FrozenFlow(sim, n_seq, 1, 1, fps, wind, 0.0, 0.0, gen, high_waves=0)
    series = []
    for _ in range(n_frames):
        series.append(state.tilt(n_seq, 1, 1)[:, :, 0, 0].double())
        state.advance(gen)
    x = torch.stack(series, 1).numpy()  # (S, T, 2): wind along x ⇒ x is parallel
    est = {
        name: np.array(
            [[1 - 0.5 * ((c[:, k:] - c[:, :-k]) ** 2).mean() for k in LAGS] for c in np.array_split(x[..., i], 10)]
        )
        for name, i in (("par", 0), ("perp", 1))
    }
    waves = FrozenFlow(sim, 200, 1, 1, fps, wind, 0.0, 0.0, gen, high_waves=0)
    cov = waves.tilt_covariance(np.zeros((len(LAGS), 2)), torch.tensor(LAGS, dtype=torch.float64)).numpy()
    perp, par = temporal_theory(LAGS, wind, fps, params.aperture_m)
    rows = []
    for j, k in enumerate(LAGS):
        rows.append(
            {
                "lag_frames": k,
                "s_aperture": round(k * wind / fps / params.aperture_m, 4),
                "theory_par": round(float(par[j]), 4),
                "frames_par": round(float(est["par"][:, j].mean()), 4),
                "se_par": round(float(est["par"][:, j].std(ddof=1) / math.sqrt(10)), 4),
                "waves_par": round(float(cov[:, j, 0, 0].mean()), 4),
                "theory_perp": round(float(perp[j]), 4),
                "frames_perp": round(float(est["perp"][:, j].mean()), 4),
                "se_perp": round(float(est["perp"][:, j].std(ddof=1) / math.sqrt(10)), 4),
                "waves_perp": round(float(cov[:, j, 1, 1].mean()), 4),
            }
        )
    return {"wind_m_s": wind, "fps": fps, "sequences": n_seq, "frames": n_frames, "table": rows}


def spatial(params, n: int, seed=0) -> dict:
    sim = Simulator(params)
    cov = sim.tilt_sampler(n, n).implied_covariance()
    ks = np.array([k for k in SEPARATIONS if k < n] + ([n - 1] if n - 1 not in SEPARATIONS else []))
    perp, par = tilt_correlation(ks * params.ifov_rad, params.aperture_m, params.path_length_m)
    state = FrozenFlow(sim, 40, 1, 1, generator=torch.Generator().manual_seed(seed), high_waves=0)
    wav = state.tilt_covariance(np.stack([0 * ks, ks], 1)).numpy()
    all_k = np.arange(1, n)
    perp_all, par_all = tilt_correlation(all_k * params.ifov_rad, params.aperture_m, params.path_length_m)
    dev_still = max(np.abs(cov[0, all_k, 0, 0] - par_all).max(), np.abs(cov[0, all_k, 1, 1] - perp_all).max())
    wav_all = state.tilt_covariance(np.stack([0 * all_k, all_k], 1)).numpy().mean(0)
    dev_seq = max(np.abs(wav_all[:, 0, 0] - par_all).max(), np.abs(wav_all[:, 1, 1] - perp_all).max())
    return {
        "size": n,
        "max_abs_dev_still": round(float(dev_still), 4),
        "max_abs_dev_sequence": round(float(dev_seq), 4),
        "table": [
            {
                "k": int(k),
                "theory_par": round(float(par[j]), 4),
                "still_par": round(float(cov[0, k, 0, 0]), 4),
                "sequence_par": round(float(wav[:, j, 0, 0].mean()), 4),
                "theory_perp": round(float(perp[j]), 4),
                "still_perp": round(float(cov[0, k, 1, 1]), 4),
                "sequence_perp": round(float(wav[:, j, 1, 1].mean()), 4),
            }
            for j, k in enumerate(ks)
        ],
    }


def figure(params, temporal_result: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sim = Simulator(params)
    fps, wind = temporal_result["fps"], temporal_result["wind_m_s"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6), dpi=100)
    t = np.arange(300) / fps
    scale = sim.tilt_std * sim.px_per_a2 * params.dr0 ** (5 / 6)
    for boil, styles in ((0.2, ("0.75", None)), (0.0, ("C0", "C1"))):
        gen = torch.Generator().manual_seed(4)
        state = FrozenFlow(sim, 1, 1, 1, fps, wind, 0.0, boil, gen, high_waves=0)
        xs = []
        for _ in range(len(t)):
            xs.append(state.tilt(1, 1, 1)[0, :, 0, 0].numpy() * scale)
            state.advance(gen)
        xs = np.array(xs)
        if boil:
            ax[0].plot(t, xs[:, 0], color=styles[0], lw=0.8, label=f"Δx with boiling {boil:g}")
        else:
            ax[0].plot(t, xs[:, 0], color=styles[0], lw=1, label="Δx, along the wind")
            ax[0].plot(t, xs[:, 1], color=styles[1], lw=1, label="Δy, across")
    ax[0].set_xlabel("time (s)")
    ax[0].set_ylabel("tilt of one pixel (px)")
    ax[0].set_title(f"D/r0 = {params.dr0:g}, wind {wind:g} m/s, {fps:g} frames/s", fontsize=9)
    ax[0].legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)
    lags = np.geomspace(0.5, 80, 200)
    perp, par = temporal_theory(lags, wind, fps, params.aperture_m)
    ax[1].semilogx(lags, par, "C0-", label="theory c∥ (I0 − I2, path)")
    ax[1].semilogx(lags, perp, "C1-", label="theory c⊥ (I0 + I2, path)")
    rows = temporal_result["table"]
    k = [r["lag_frames"] for r in rows]
    ax[1].errorbar(k, [r["frames_par"] for r in rows], [2 * r["se_par"] for r in rows], fmt="C0o", ms=4)
    ax[1].errorbar(k, [r["frames_perp"] for r in rows], [2 * r["se_perp"] for r in rows], fmt="C1s", ms=4)
    ax[1].plot([], [], "ko", ms=4, label="simulated (±2 SE)")
    ax[1].set_xlabel("lag (frames)")
    ax[1].set_ylabel("temporal correlation of a pixel's tilt")
    ax[1].set_ylim(0, 1.02)
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def animation(path: str, frames: int = 36, size: int = 120) -> None:
    """Two scenes side by side (a photo and a chart of straight lines), D/r0 = 3, wind 1 m/s at 30 fps."""
    from PIL import Image
    from skimage import data, transform

    photo = transform.resize(data.astronaut()[:400, 60:460], (size, size), anti_aliasing=True)
    chart = np.ones((size, size, 3))
    for i in range(8, size, 16):
        chart[i : i + 2, :] = 0.15
        chart[:, i : i + 2] = 0.15
    img = torch.from_numpy(np.concatenate([photo, chart], 1)).float().permute(2, 0, 1)
    sim = Simulator(TurbulenceParams(dr0=3.0))
    gen = torch.Generator().manual_seed(0)
    out = []
    for res in sim.sequence(img, frames=frames, fps=30, wind=1.0, wind_dir=20, generator=gen):
        arr = (res.turb[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        out.append(Image.fromarray(arr).convert("P", palette=Image.Palette.ADAPTIVE, colors=96))
    out[0].save(path, save_all=True, append_images=out[1:], duration=1000 // 15, loop=0, optimize=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, metavar="FILE")
    ap.add_argument("--figure", default="docs/images/video_tilt.png")
    ap.add_argument("--gif", default="docs/images/video_demo.gif")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--figures-from", default=None, metavar="JSON", help="only redraw the images from a report")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    params = TurbulenceParams(dr0=3.0)
    start = time.perf_counter()
    if args.figures_from:
        report = json.loads(open(args.figures_from).read())
        args.json = None
    else:
        report = {"benchmark": "video_physics", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
        report["temporal"] = temporal(params, wind=1.0, fps=30.0)
        print(json.dumps(report["temporal"], indent=1), flush=True)
        report["spatial"] = [spatial(params, n) for n in (256, 512)]
        print(json.dumps(report["spatial"], indent=1), flush=True)
    if args.figure:
        figure(params, report["temporal"], args.figure)
    if args.gif:
        animation(args.gif)
    report["seconds"] = round(time.perf_counter() - start, 1)
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
