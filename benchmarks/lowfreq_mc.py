"""Monte-Carlo check of the tilt field's lowest frequencies (issue 14): many generated fields, compared
with the path-integrated I0 ± I2 theory. A statistics run, not a timing: run it once, niced.

    nice -n 19 python3 benchmarks/lowfreq_mc.py --sizes 256 512 --fields 4000 2000 --json lowfreq.json

For each size and each synthesis (``periodic``: the plain torus of period 2N, as before subharmonics;
``subharmonic``: the default still sampler; ``sequence``: frames of independent frozen-flow sequences)
it reports, with standard errors from batch means:
the per-pixel tilt RMS, the variance of the image-mean tilt, and the parallel / perpendicular
correlation at every separation k = 1 … N−1 along both axes, each against theory. It also gives the
exact covariance the still samplers realise (from their spectrum, no sampling error) at the same
separations; for sequences, the covariance given their plane waves, averaged over the sequences drawn.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import numpy as np
import torch

from d2turb.io import write_json
from d2turb.sim import Simulator, TurbulenceParams
from d2turb.sim.fields import VectorFieldSampler
from d2turb.sim.sequence import FrozenFlow
from d2turb.sim.tilt import tilt_correlation


def theory(n: int, params: TurbulenceParams) -> dict:
    """Axis correlations c∥, c⊥ (k = 0 … n−1) and the variance of the n×n image mean of one component."""
    k = np.arange(n)
    perp, par = tilt_correlation(k * params.ifov_rad, params.aperture_m, params.path_length_m)
    d = np.arange(-(n - 1), n)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    r = np.hypot(dx, dy)
    cp, cl = tilt_correlation(r * params.ifov_rad, params.aperture_m, params.path_length_m)
    ux2 = np.where(r > 0, dx**2 / np.maximum(r, 1e-9) ** 2, 0.5)
    cxx = cp + (cl - cp) * ux2
    w = np.outer(n - np.abs(d), n - np.abs(d)) / float(n) ** 4
    return {"par": par, "perp": perp, "mean_var": float((w * cxx).sum())}


def structure_sums(fields: torch.Tensor) -> torch.Tensor:
    """Σ over fields and lines of (t(x+k) − t(x))², k = 0 … n−1, along x and along y: (2 comps, 2 dirs, n).

    The correlation estimate is c(k) = 1 − ½·mean((t(x+k) − t(x))²) (the variance is 1 by construction and
    is checked separately): unlike the plain product mean, it is not swamped by the image-scale fluctuation."""
    n = fields.shape[-1]
    out = []
    for f in (fields, fields.transpose(-1, -2)):  # along x, then along y
        f = f.double()
        spec = torch.fft.rfft(f, n=2 * n, dim=-1)
        ac = torch.fft.irfft(spec.abs() ** 2, n=2 * n, dim=-1)[..., :n]  # Σ_x t(x) t(x+k)
        sq = torch.cumsum(f**2, dim=-1)
        head = sq.flip(-1)  # Σ_{x < n−k} t(x)²  at index k
        tail = sq[..., -1:] - torch.cat([torch.zeros_like(sq[..., :1]), sq[..., :-1]], -1)  # Σ_{x ≥ k} t(x)²
        out.append((head + tail - 2 * ac).sum(dim=(0, 2)))  # (2 comps, n)
    return torch.stack(out, 1)


def run(n: int, n_fields: int, synthesis: str, batch: int, seed: int) -> dict:
    sim = Simulator(TurbulenceParams())
    gen = torch.Generator().manual_seed(seed)
    k = np.arange(n)
    if synthesis == "sequence":
        # one frame of each of `batch` independent frozen-flow sequences per batch
        def draw():
            state = FrozenFlow(sim, batch, n, n, generator=gen, high_waves=0)
            cond.append(state.tilt_covariance(np.stack([0 * k, k], 1)).mean(0).numpy())
            return state.tilt(batch, n, n)

        cond: list = []
    else:
        sampler = VectorFieldSampler(n, n, sim.tilt_layers(), levels=0) if synthesis == "periodic" else None
        sampler = sampler or sim.tilt_sampler(n, n)
        exact = sampler.implied_covariance()

        def draw():
            return sampler.sample(batch, gen)

    sq, means, acs = [], [], []
    start = time.perf_counter()
    for _ in range(n_fields // batch):
        f = draw().double()  # (B, 2, n, n)
        sq.append((f**2).mean(dim=(0, 2, 3)).numpy())
        means.append(f.mean(dim=(2, 3)).numpy())
        acs.append(1 - 0.5 * structure_sums(f).numpy() / (batch * n * (n - np.arange(n))))
    seconds = time.perf_counter() - start
    sq, means, acs = np.array(sq), np.concatenate(means), np.array(acs)  # (nb, 2), (F, 2), (nb, 2, 2, n)
    nb = len(sq)
    rms = np.sqrt(sq.mean())
    rms_se = sq.mean(1).std(ddof=1) / np.sqrt(nb) / (2 * rms)
    mv = (means**2).mean()
    mv_se = (means**2).mean(1).reshape(nb, -1).mean(1).std(ddof=1) / np.sqrt(nb)
    corr, corr_se = acs.mean(0), acs.std(0, ddof=1) / np.sqrt(nb)
    # parallel: x-component along x and y-component along y; perpendicular: the other two
    par = 0.5 * (corr[0, 0] + corr[1, 1])
    perp = 0.5 * (corr[1, 0] + corr[0, 1])
    par_se = 0.5 * np.sqrt(corr_se[0, 0] ** 2 + corr_se[1, 1] ** 2)
    perp_se = 0.5 * np.sqrt(corr_se[1, 0] ** 2 + corr_se[0, 1] ** 2)
    if synthesis == "sequence":  # the covariance given the drawn plane waves, averaged over the sequences
        c = np.mean(cond, 0)
        ex_par, ex_perp = c[:, 0, 0], c[:, 1, 1]
    else:
        ex_par = 0.5 * (exact[0, k, 0, 0] + exact[k, 0, 1, 1])
        ex_perp = 0.5 * (exact[0, k, 1, 1] + exact[k, 0, 0, 0])
    return dict(
        fields=nb * batch,
        seconds=round(seconds, 1),
        rms=rms,
        rms_se=rms_se,
        mean_var=mv,
        mean_var_se=mv_se,
        par=par,
        perp=perp,
        par_se=par_se,
        perp_se=perp_se,
        exact_par=ex_par,
        exact_perp=ex_perp,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--fields", type=int, nargs="+", default=[4000, 2000], help="fields per size")
    ap.add_argument("--batch", type=int, default=40)
    ap.add_argument("--synthesis", nargs="+", default=["periodic", "subharmonic", "sequence"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    params = TurbulenceParams()
    report = {
        "benchmark": "lowfreq_mc",
        "params": "D = 0.1 m, λ = 525 nm, L = 1 km, Nyquist pixels, path geometry (48 layers)",
        "machine": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "results": [],
    }
    marks = [1, 8, 32, 64, 128, 192, 224, 256, 320, 384, 448, 480, 511]
    for n, n_fields in zip(args.sizes, args.fields):
        th = theory(n, params)
        for name in args.synthesis:
            r = run(n, n_fields, name, args.batch, args.seed + n)
            ks = np.arange(1, n)
            d_par, d_perp = r["par"][ks] - th["par"][ks], r["perp"][ks] - th["perp"][ks]
            e_par, e_perp = r["exact_par"][ks] - th["par"][ks], r["exact_perp"][ks] - th["perp"][ks]
            row = {
                "size": n,
                "synthesis": name,
                "fields": r["fields"],
                "seconds": r["seconds"],
                "rms_ratio": round(float(r["rms"]), 4),
                "rms_se": round(float(r["rms_se"]), 4),
                "image_mean_var_ratio": round(float(r["mean_var"] / th["mean_var"]), 4),
                "image_mean_var_ratio_se": round(float(r["mean_var_se"] / th["mean_var"]), 4),
                "max_abs_dev_par": round(float(np.abs(d_par).max()), 4),
                "max_abs_dev_perp": round(float(np.abs(d_perp).max()), 4),
                "max_se_corr": round(float(max(r["par_se"][ks].max(), r["perp_se"][ks].max())), 4),
                "exact_max_abs_dev": round(float(max(np.abs(e_par).max(), np.abs(e_perp).max())), 4),
                "table": [
                    {
                        "k": k,
                        "theory_par": round(float(th["par"][k]), 4),
                        "mc_par": round(float(r["par"][k]), 4),
                        "se_par": round(float(r["par_se"][k]), 4),
                        "exact_par": round(float(r["exact_par"][k]), 4),
                        "theory_perp": round(float(th["perp"][k]), 4),
                        "mc_perp": round(float(r["perp"][k]), 4),
                        "se_perp": round(float(r["perp_se"][k]), 4),
                        "exact_perp": round(float(r["exact_perp"][k]), 4),
                    }
                    for k in marks + [n - 1]
                    if k < n
                ],
            }
            report["results"].append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "table"}), flush=True)
    text = json.dumps(report, indent=2)
    if args.json:
        write_json(args.json, report)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
