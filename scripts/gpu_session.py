"""The whole GPU lease as one prepared command (docs/training.md, "The 15-minute lease").

    timeout -k 15 560 python3 scripts/gpu_session.py --out "$OUT"          # on the lent GPU (scripts/gpu_session.sh)
    python3 scripts/gpu_session.py --rehearsal --out /tmp/rehearsal         # the same steps on a CPU, tiny sizes

Steps, each logged with its wall time: (1) check the device and the project's imports; (2) use the carried training
pack, or build one (the rehearsal builds a tiny one from scikit-image's photographs through the same ``make_pack``);
(3) measure each candidate's training throughput, all candidates at once so that the rates include their sharing of
the device (``benchmarks/bench_train.py``; a candidate whose bf16/channels_last bench fails is benched again in
float32); (4) train the candidates side by side, each for ``iterations = images/s × seconds × SAFETY / batch`` so its
cosine schedule ends inside the budget, with ``train.max_minutes`` and, after it, SIGTERM and SIGKILL as hard stops;
(5) bring back, per candidate, one tar of ``best.safetensors`` (+ ``model.safetensors`` where it fits 15 MiB),
``log.jsonl``, ``status.json``, ``config.yaml`` and the training log, and ``gpu_session.json`` with the checks, the
rates, the planned and reached iterations and the last validation per bin. At most 8 files of ≤ 15 MiB come back.

Every deadline is counted from this script's start (``--budget-s``), so the command ends on its own inside the
lease's call limit; a candidate that fails does not stop the others, and whatever exists at the end is collected.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAFETY = 0.8  # share of the measured rate planned for: the rates move when the candidates start and stop
TAR_LIMIT = 15 * 2**20  # what comes back: files ≤ 16 MiB
# images/s assumed where a bench did not finish in time (train.max_minutes still stops the run): about 2 % of an H100's
# bf16 rate at the forward + backward cost of each model (3 × its forward FLOPs per 256² image: 7.8, 17.0, 20.7 G)
ASSUMED_RATE = {"nafnet_ft": 2000.0, "nafnet_w24": 900.0, "d2turb_small": 750.0}

# name: (config, bench model, bench model config as JSON); the candidates of docs/training.md "The 15-minute lease"
CANDIDATES = {
    "nafnet_ft": ("configs/gpu_nafnet_ft.yaml", "nafnet", "{}"),
    "nafnet_w24": ("configs/gpu_nafnet_w24.yaml", "nafnet", '{"width": 24}'),
    "d2turb_small": ("configs/d2turb_small_gpu.yaml", "d2turb_small", "{}"),
}
# the rehearsal: the same steps on a CPU at sizes that take seconds
REHEARSAL_SET = [
    "train.device=cpu",
    "train.batch=2",
    "data.patch=48",
    "val.crop=48",
    "val.batch=4",
    "val.every=1000",  # validated once, at the end, as on the device
    "checkpoint.every=1000",
    "log.every=1",
    "train.amp=null",
    "train.channels_last=false",
]


class Session:
    def __init__(self, out: Path, budget_s: float, rehearsal: bool):
        self.t0 = time.monotonic()
        self.out, self.budget_s, self.rehearsal = out, budget_s, rehearsal
        self.report: dict = {"rehearsal": rehearsal, "budget_s": budget_s, "steps": {}, "candidates": {}}
        self.log_file = open(out / "gpu_session.log", "a", buffering=1)

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def left(self) -> float:
        return self.budget_s - self.elapsed()

    def log(self, msg: str) -> None:
        line = f"[{self.elapsed():6.1f} s] {msg}"
        print(line, flush=True)
        self.log_file.write(line + "\n")

    def step(self, name: str, **values) -> None:
        self.report["steps"][name] = {"at_s": round(self.elapsed(), 1), **values}
        self.save()

    def save(self) -> None:
        tmp = self.out / ".gpu_session.json.tmp"
        tmp.write_text(json.dumps(self.report, indent=2))
        os.replace(tmp, self.out / "gpu_session.json")


def env(threads: int) -> dict[str, str]:
    e = dict(os.environ, PYTHONPATH=str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", ""))
    e["PYTHONUNBUFFERED"] = "1"
    e["OMP_NUM_THREADS"] = str(threads)  # the candidates run side by side: no oversubscribed OpenMP spinning
    return e


def check_device(s: Session) -> str:
    import torch

    info = {"torch": torch.__version__, "python": platform.python_version(), "cuda": torch.cuda.is_available()}
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        info |= {"gpu": props.name, "gpu_mib": props.total_memory // 2**20, "sms": props.multi_processor_count}
        info["bf16"] = torch.cuda.is_bf16_supported()
    import d2turb.models  # noqa: F401  the project imports on this host
    import d2turb.train  # noqa: F401

    s.step("check", **info)
    s.log(f"check: {json.dumps(info)}")
    if not s.rehearsal and not torch.cuda.is_available():
        raise SystemExit("error: no CUDA device on this host (use --rehearsal on a CPU)")
    return "cpu" if s.rehearsal else "cuda"


def tiny_clean(folder: Path) -> Path:
    """Four scikit-image photographs as a train folder and one as a val folder (set14 is a val folder by name)."""
    import numpy as np
    from PIL import Image
    from skimage import data

    for split, names in (("urban100", ("astronaut", "coffee", "chelsea")), ("set14", ("rocket",))):
        (folder / split).mkdir(parents=True, exist_ok=True)
        for name in names:
            image = Image.fromarray(np.asarray(getattr(data, name)())[..., :3])
            image.thumbnail((160, 160))
            image.save(folder / split / f"{name}.png")
    return folder


def ensure_pack(s: Session, pack: Path, clean: Path | None) -> Path:
    if (pack / "pack.json").is_file():
        s.step("pack", carried=True, path=str(pack))
        s.log(f"pack: carried ({pack})")
        return pack
    from d2turb.data.pack import make_pack

    if clean is None:
        clean = tiny_clean(s.out / "clean") if s.rehearsal else ROOT.parent / "shared" / "data" / "clean"
    if not clean.is_dir():
        raise SystemExit(f"error: no pack at {pack} and no clean images at {clean}: carry packs/ (make-pack)")
    info = make_pack([clean], pack, patch=48 if s.rehearsal else 256)
    s.step("pack", carried=False, built_from=str(clean), images=info.get("images"))
    s.log(f"pack: built from {clean}: {info.get('images')}")
    return pack


def run_all(s: Session, jobs: dict[str, list[str]], logs: dict[str, Path], deadline_s: float) -> dict[str, int | None]:
    """Start every job at once; SIGTERM at the deadline, SIGKILL 20 s later. Returns exit codes (None: killed)."""
    procs = {}
    for name, argv in jobs.items():
        logs[name].parent.mkdir(parents=True, exist_ok=True)
        with open(logs[name], "ab") as f:
            threads = 1 if s.rehearsal else 4
            procs[name] = subprocess.Popen(argv, cwd=ROOT, env=env(threads), stdout=f, stderr=subprocess.STDOUT)
    termed = killed = False
    while any(p.poll() is None for p in procs.values()):
        if not termed and s.elapsed() > deadline_s:
            s.log("deadline: SIGTERM")
            termed = True
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
        if termed and not killed and s.elapsed() > deadline_s + 20:
            s.log("deadline + 20 s: SIGKILL")
            killed = True
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
        time.sleep(0.5)
    return {name: p.returncode for name, p in procs.items()}


def bench(s: Session, names: list[str], pack: Path, runs: Path, device: str, fallback: bool) -> dict[str, dict]:
    jobs, logs = {}, {}
    for name in names:
        _, model, model_cfg = CANDIDATES[name]
        cfg = _config(name)
        argv = [sys.executable, str(ROOT / "benchmarks" / "bench_train.py"), "--model", model, "--model-cfg", model_cfg]
        argv += ["--pack", str(pack), "--device", device, "--json", str(runs / f"bench_{name}.json")]
        if s.rehearsal:
            argv += ["--patch", "48", "--batch", "2", "--steps", "2", "--warmup", "1", "--threads", "1"]
        else:
            argv += ["--patch", str(cfg["data"]["patch"]), "--batch", str(cfg["train"]["batch"])]
            argv += ["--steps", "20", "--warmup", "5", "--threads", "4", "--ema", "0.999"]
            if not fallback:
                argv += ["--amp", "bf16", "--channels-last"]
        jobs[name], logs[name] = argv, runs / f"bench_{name}.log"
    codes = run_all(s, jobs, logs, deadline_s=s.elapsed() + 120)
    results = {}
    for name, code in codes.items():
        path = runs / f"bench_{name}.json"
        if code == 0 and path.is_file():
            results[name] = json.loads(path.read_text())["result"]
        else:
            results[name] = {"failed": code, "log_tail": _tail(logs[name])}
    return results


def _broken(result: dict) -> bool:
    """A bench that exited with an error (not one stopped at its deadline: that one was only slow)."""
    return "failed" in result and result["failed"] not in (None, -signal.SIGTERM, -signal.SIGKILL)


def _config(name: str) -> dict:
    import yaml

    return yaml.safe_load((ROOT / CANDIDATES[name][0]).read_text())


def _tail(path: Path, n: int = 1500) -> str:
    return path.read_text(errors="replace")[-n:] if path.is_file() else ""


def last_validation(run: Path) -> dict:
    best, last = None, None
    log = run / "log.jsonl"
    if log.is_file():
        for line in log.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if "val_psnr" in rec:
                last = rec
                if best is None or rec["val_psnr"] > best["val_psnr"]:
                    best = rec
    keep = lambda r: r and {k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}  # noqa: E731
    return {"last": keep(last), "best": keep(best)}


def collect(s: Session, name: str, run: Path) -> None:
    members = [run / f for f in ("best.safetensors", "log.jsonl", "status.json", "config.yaml", "train.log")]
    members = [m for m in members if m.is_file()]
    extra = run / "model.safetensors"
    if extra.is_file() and sum(m.stat().st_size for m in members) + extra.stat().st_size < TAR_LIMIT:
        members.append(extra)
    if not members:
        return
    target = s.out / f"{name}.tar"
    with tarfile.open(target, "w") as tar:
        for m in members:
            tar.add(m, arcname=f"{name}/{m.name}")
    if target.stat().st_size > TAR_LIMIT:  # never here for the shipped candidates (≤ 2.6 M parameters)
        s.log(f"collect: {target.name} is over 15 MiB and will not come back")
    s.log(f"collect: {target.name} ({target.stat().st_size / 2**20:.1f} MiB: {', '.join(m.name for m in members)})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the folder that comes back ($OUT on the device)")
    ap.add_argument("--pack", default=None, help="training pack (default packs/clean, carried; built when missing)")
    ap.add_argument("--clean", default=None, help="clean images to build the pack from when it is missing")
    ap.add_argument("--runs", default="runs/lease", help="run folders (not brought back whole)")
    ap.add_argument(
        "--candidates",
        default="nafnet_ft",
        help=f"comma-separated names of {', '.join(CANDIDATES)}; side by side they share the device (docs/training.md)",
    )
    ap.add_argument("--budget-s", type=float, default=530.0, help="this script's wall time, start to end")
    ap.add_argument("--rehearsal", action="store_true", help="the same steps on a CPU at tiny sizes")
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override for every candidate's training (e.g. train.init_from=FILE for a second lease)",
    )
    ap.add_argument(
        "--rate",
        dest="rates",
        action="append",
        default=[],
        metavar="NAME=IMAGES_PER_S",
        help="a candidate's training rate measured before on this kind of device (gpu_session.json of a previous "
        "lease): its bench is skipped (about 20-35 s of device time); train.max_minutes still stops it in time",
    )
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s = Session(out, args.budget_s, args.rehearsal)
    names = [n for n in args.candidates.split(",") if n]
    try:
        given = {k: float(v) for k, v in (r.split("=", 1) for r in args.rates)}
    except ValueError:
        print(f"error: --rate takes NAME=IMAGES_PER_S, got {args.rates}", file=sys.stderr)
        return 2
    if any(not (v > 0) for v in given.values()) or set(given) - set(names):
        print(f"error: --rate needs a positive rate for a chosen candidate, got {args.rates}", file=sys.stderr)
        return 2
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        print(f"error: unknown candidate(s) {', '.join(unknown)}; known: {', '.join(CANDIDATES)}", file=sys.stderr)
        return 2
    runs = (ROOT / args.runs).resolve()
    if runs.exists():
        shutil.rmtree(runs)  # a fresh machine has none; a second rehearsal starts clean
    runs.mkdir(parents=True)
    try:
        device = check_device(s)
        pack = args.pack or (str(runs / "pack") if s.rehearsal else "packs/clean")  # the rehearsal builds its own
        pack = ensure_pack(s, (ROOT / pack).resolve(), Path(args.clean) if args.clean else None)

        measure = [n for n in names if n not in given]
        rates = bench(s, measure, pack, runs, device, fallback=False) if measure else {}
        rates |= {n: {"images_per_s": r, "given": True} for n, r in given.items()}
        failed = [n for n in names if _broken(rates[n])]
        if failed and not s.rehearsal:
            s.log(f"bench failed for {failed} with bf16/channels_last: again in float32")
            for n, r in bench(s, failed, pack, runs, device, fallback=True).items():
                rates[n] = r | {"fallback_float32": True}
        s.step("bench", results=rates)
        for n in names:
            s.log(f"bench {n}: {json.dumps(rates[n])[:300]}")

        end_train_s = s.budget_s - (25 if s.rehearsal else 60)  # leave time to stop, write and collect
        jobs, logs = {}, {}
        for n in names:
            if "failed" in rates[n]:
                if _broken(rates[n]) or s.rehearsal:
                    continue  # broken, not slow
                rates[n] |= {"images_per_s": ASSUMED_RATE[n], "assumed": True}  # the bench ran out of time
            cfg = _config(n)
            minutes = (end_train_s - s.elapsed() - (5 if s.rehearsal else 30)) / 60  # start-up: imports, pack decode
            batch = 2 if s.rehearsal else cfg["train"]["batch"]
            planned = max(1, int(rates[n]["images_per_s"] * 60 * minutes * SAFETY / batch))
            if s.rehearsal:
                planned = min(planned, 4)
            sets = [f"train.iterations={planned}", f"train.max_minutes={max(minutes, 0.05):.3f}"]
            sets += [f"data.pack={pack}", f"val.pack={pack}"]
            sets += args.overrides
            if s.rehearsal:
                sets += REHEARSAL_SET
            elif rates[n].get("fallback_float32"):
                sets += ["train.amp=null", "train.channels_last=false"]
            jobs[n] = [sys.executable, "-m", "d2turb", "train", "--config", str(ROOT / CANDIDATES[n][0])]
            jobs[n] += ["--out", str(runs / n)] + [a for kv in sets for a in ("--set", kv)]
            logs[n] = runs / n / "train.log"
            s.report["candidates"][n] = {"planned_iterations": planned, "minutes": round(minutes, 2), "set": sets}
            s.log(f"train {n}: {planned} iterations in ≤ {minutes:.2f} min")
        s.step("train_start")
        codes = run_all(s, jobs, logs, deadline_s=end_train_s)
        for n, code in codes.items():
            status_file = runs / n / "status.json"
            status = json.loads(status_file.read_text()) if status_file.is_file() else {}
            s.report["candidates"][n] |= {
                "exit": code,
                "state": status.get("state"),
                "iteration": status.get("iteration"),
                "validation": last_validation(runs / n),
                "log_tail": _tail(logs[n], 600) if code != 0 else "",
            }
            s.log(f"trained {n}: exit {code}, {status.get('state')} at iteration {status.get('iteration')}")
        s.step("train_end")
    finally:
        for n in names:
            if (runs / n).is_dir():
                collect(s, n, runs / n)
        s.step("collected")
        table = ["candidate      exit  iters  val PSNR weak/medium/strong (input)"]
        for n, c in s.report["candidates"].items():
            v = (c.get("validation") or {}).get("last") or {}
            psnr = "/".join(f"{v.get(f'val_psnr_{b}', float('nan')):.3f}" for b in ("weak", "medium", "strong"))
            inp = "/".join(f"{v.get(f'val_psnr_input_{b}', float('nan')):.3f}" for b in ("weak", "medium", "strong"))
            table.append(f"{n:<14} {c.get('exit')!s:>4} {c.get('iteration')!s:>6}  {psnr} ({inp})")
        s.log("summary\n" + "\n".join(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
