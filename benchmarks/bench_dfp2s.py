"""d2turb's simulator against DF-P2S (Chimitt et al., as shipped in xg416/MambaTM), interleaved in one process.

    python3 benchmarks/bench_dfp2s.py --dfp2s /path/to/MambaTM [--size 256] [--batch 8] [--rounds 3]
        [--threads 2] [--dr0 3] [--json FILE]

DF-P2S is not a dependency: give the path of a MambaTM checkout (or of its ``code/LPD_learning`` folder, which
holds ``utils/simulator.py`` and ``utils/precomputed/*.pt*``); without it the script prints a JSON line with
``"skipped"`` and exits 0. Both simulators get the same optics: D = 0.1 m, λ = 525 nm, L = 1 km, Nyquist
pixels (ifov = λ/2D), 36 Zernike modes, D/r0 = 3 (DF-P2S: a constant Cn² over 10 layers chosen by its own
r0 formula), RGB images, one batch per call, no gradients. DF-P2S's kernel size follows its own rule
(commented out in its source): 65·(third diffraction ring in pixels)/10·max(1, min(2, D/r0 / 4)), made odd.

Each round times one DF-P2S call and ``--d2turb-calls`` d2turb calls (alternating which goes first), after one
warm-up call of each; the ratio is taken per round, so both see the same load. Wall time is the headline;
process CPU time is reported too (it counts every thread, so it is the fairer figure on a busy machine).
Prints one JSON object (and writes it to --json FILE).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from d2turb.io import write_json
from d2turb.sim import Simulator, TurbulenceParams

D, WAVELENGTH, RANGE = 0.1, 525e-9, 1000.0


def dfp2s_folder(path: str | None) -> Path | None:
    """The folder holding ``utils/simulator.py`` and ``utils/precomputed``, or None."""
    if not path:
        return None
    for cand in (Path(path), Path(path) / "code" / "LPD_learning"):
        if (cand / "utils" / "simulator.py").is_file() and (cand / "utils" / "precomputed").is_dir():
            return cand
    return None


def dfp2s_kernel_size(dr0: float, size: int) -> int:
    """DF-P2S's own kernel-size rule (utils/simulator.py, _blur_construct, commented out there)."""
    ifov = WAVELENGTH / (2 * D)
    dx = size * ifov * RANGE / size  # metres per pixel at the object
    third_ring = 3 * 1.22 * WAVELENGTH * RANGE / D
    ks = round((third_ring / dx) / 10 * 65 * min(2, max(1, dr0 / 4)))
    return ks + 1 - ks % 2


def dfp2s_params(size: int, batch: int, dr0: float, temp_corr: float = 0.0, layers: int = 10) -> tuple[dict, float]:
    """DF-P2S's simulator settings for our optics at D/r0 ``dr0`` (a constant Cn² over ``layers`` layers), and that
    Cn²."""
    k = 2 * math.pi / WAVELENGTH
    lm = sum(((i + 1) / (layers + 1)) ** (5 / 3) for i in range(layers))
    cn2 = (D / dr0) ** (-5 / 3) / (0.423 * k * k * RANGE / layers * lm)  # inverts DF-P2S's r0 formula (turb.py)
    width = size * WAVELENGTH / (2 * D) * RANGE
    params = dict(
        img_shape=(size, size),
        batch_size=batch,
        L=RANGE,
        f=0.3,
        wvl=WAVELENGTH,
        width=width,
        D=D,
        anti_aliasing_range=width,
        Cn2=torch.full((layers,), cn2),
        temp_corr=temp_corr,
        num_zern=36,
        kernel_size=dfp2s_kernel_size(dr0, size),
    )
    return params, cn2


def make_dfp2s(folder: Path, size: int, batch: int, dr0: float):
    sys.path.insert(0, str(folder))
    from utils.simulator import Simulator as DFP2S  # noqa: PLC0415  (third-party code, imported from its path)

    params, _ = dfp2s_params(size, batch, dr0)
    sim = DFP2S(str(folder / "utils"), params)
    return sim, float(sim.Dr0), params["kernel_size"]


def timed(fn, calls: int) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(calls):
        fn()
    return time.perf_counter() - wall, time.process_time() - cpu


def _rounded(v):
    return {k: round(x, 2) for k, x in v.items()} if isinstance(v, dict) else round(v, 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dfp2s", default=os.environ.get("DFP2S_PATH"), help="MambaTM checkout (or $DFP2S_PATH)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--d2turb-calls", type=int, default=4, help="d2turb calls per round")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dr0", type=float, default=3.0)
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    folder = dfp2s_folder(args.dfp2s)
    if folder is None:
        print(json.dumps({"benchmark": "sim_vs_dfp2s", "skipped": f"no DF-P2S checkout at {args.dfp2s!r}"}))
        return 0
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    ref, ref_dr0, ks = make_dfp2s(folder, args.size, args.batch, args.dr0)
    sim = Simulator(TurbulenceParams(dr0=args.dr0))
    img = torch.rand(args.batch, 3, args.size, args.size, generator=torch.Generator().manual_seed(0))
    gen = torch.Generator().manual_seed(1)

    def run_ours():
        sim(img, generator=gen)

    def run_ref():
        ref(img)

    rounds = []
    with torch.no_grad():
        run_ours(), run_ref()  # warm-up: cached spectra, optics, DF-P2S's first-call set-up
        for r in range(args.rounds):
            order = [("d2turb", run_ours, args.d2turb_calls), ("dfp2s", run_ref, 1)]
            res = {}
            for name, fn, calls in order if r % 2 == 0 else order[::-1]:
                wall, cpu = timed(fn, calls)
                n = calls * args.batch
                res[name] = {"ms_per_image": 1000 * wall / n, "cpu_ms_per_image": 1000 * cpu / n}
            res["ratio"] = res["dfp2s"]["ms_per_image"] / res["d2turb"]["ms_per_image"]
            res["cpu_ratio"] = res["dfp2s"]["cpu_ms_per_image"] / res["d2turb"]["cpu_ms_per_image"]
            res["load1"] = os.getloadavg()[0]
            rounds.append(res)

    def med(key, sub=None):
        return round(statistics.median(r[key] if sub is None else r[key][sub] for r in rounds), 2)

    report = {
        "benchmark": "sim_vs_dfp2s",
        "size": args.size,
        "batch": args.batch,
        "dr0": args.dr0,
        "dfp2s_dr0": round(ref_dr0, 3),
        "dfp2s_kernel_size": ks,
        "threads": args.threads,
        "d2turb_ms_per_image": med("d2turb", "ms_per_image"),
        "dfp2s_ms_per_image": med("dfp2s", "ms_per_image"),
        "ratio_median": med("ratio"),
        "cpu_ratio_median": med("cpu_ratio"),
        "rounds": [{k: _rounded(v) for k, v in r.items()} for r in rounds],
        "load_before": [round(v, 2) for v in load_before],
        "load_after": [round(v, 2) for v in os.getloadavg()],
        "torch": torch.__version__,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
