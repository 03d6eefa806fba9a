"""The whole GPU lease as one prepared command (docs/training.md, "The 15-minute lease").

    timeout -k 15 560 python3 scripts/gpu_session.py --out "$OUT"          # on the lent GPU (scripts/gpu_session.sh)
    python3 scripts/gpu_session.py --unpack DIR                             # here: what came back → runs/carry/
    python3 scripts/gpu_session.py --carry-size packs runs/carry            # here: what the next call would carry
    python3 scripts/gpu_session.py --rehearsal --out /tmp/rehearsal         # the same steps on a CPU, tiny sizes

Training spans leases: a candidate whose ``runs/carry/NAME/model.safetensors`` (``--carry``) is on the host starts
from those weights (``train.init_from``; otherwise from its config's ``init_from``: ``d2turb_small``'s backbone from
the shipped NAFNet) with the next seed, and ``lease_state.json`` beside them, extended by each call, records every
call so far. ``--unpack`` puts a call's tar back into ``runs/carry/`` here; carry ``runs/carry`` (≈ 10 MiB for
``d2turb_small``) into the next call. Each call is a whole cosine cycle (a warm restart): ``last.pt`` with Adam's
moments (41 MB for ``d2turb_small``) neither comes back as one file nor fits the carry beside the pack.

Steps, each logged with its wall time: (1) check the device and the project's imports; (2) use the carried training
pack, or build one (the rehearsal builds a tiny one from scikit-image's photographs through the same ``make_pack``);
(3) measure each candidate's training throughput, all candidates at once so that the rates include their sharing of
the device (``benchmarks/bench_train.py``; a candidate whose bf16/channels_last bench fails is benched again in
float32); (4) train the candidates side by side, each for ``iterations = images/s × seconds × SAFETY / batch`` so its
cosine schedule ends inside the budget, with ``train.max_minutes`` and, after it, SIGTERM and SIGKILL as hard stops;
(5) bring back, per candidate, one tar of the final weights ``model.safetensors`` (what the next call continues from),
``lease_state.json``, ``log.jsonl``, ``status.json``, ``config.yaml`` and the training log (+ ``best.safetensors``
where it differs and fits 15 MiB, else in ``NAME_best.tar`` while the 8 files allow), and ``gpu_session.json`` with
the checks, the rates, the start, the planned and reached iterations and the last validation per bin. At most 8 files
of ≤ 15 MiB come back.

Every deadline is counted from this script's start (``--budget-s``), so the command ends on its own inside the
lease's call limit; a candidate that fails does not stop the others, and whatever exists at the end is collected.
"""

from __future__ import annotations

import argparse
import hashlib
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
MAX_FILES = 8  # what comes back: at most 8 files
CARRY_LIMIT = 64 * 2**20  # what a call carries: the checkout and the named ignored paths together
CARRY = "runs/carry"  # per candidate: model.safetensors + lease_state.json, the state one call leaves the next
SEED_STRIDE = 1009  # train.seed of call k (0-based) = the config's seed + k * SEED_STRIDE: new crops and turbulence
# images/s assumed where a bench did not finish in time (train.max_minutes still stops the run): what the H200 leases
# measured (nafnet_ft 369-397 alone; nafnet_w24 148 and d2turb_small 72 with three candidates sharing the device, so
# about 3x that alone), rounded down so that the cosine schedule ends inside the budget
ASSUMED_RATE = {"nafnet_ft": 350.0, "nafnet_w24": 400.0, "d2turb_small": 200.0}

# name: (config, bench model, bench model config as JSON); the candidates of docs/training.md "The 15-minute lease"
CANDIDATES = {
    "nafnet_ft": ("configs/gpu_nafnet_ft.yaml", "nafnet", "{}"),
    "nafnet_w24": ("configs/gpu_nafnet_w24.yaml", "nafnet", '{"width": 24}'),
    "d2turb_small": ("configs/d2turb_small_gpu.yaml", "d2turb_small", "{}"),
}
DEFAULT_CANDIDATES = "d2turb_small"
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


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(2**20), b""):
            h.update(block)
    return h.hexdigest()


def _tensors_sha256(path: Path) -> str | None:
    """The checksum save_pretrained keeps of a file's tensors (its JSON header's key order varies between writes)."""
    from safetensors import safe_open

    with safe_open(str(path), "pt") as f:
        return (f.metadata() or {}).get("d2turb_sha256")


def start_state(name: str, carry: Path, overrides: list[str]) -> tuple[list[str], dict]:
    """Where candidate ``name`` starts: the carried ``carry/NAME/model.safetensors`` with its ``lease_state.json``
    (the calls so far), else its config's ``init_from``. Returns (the --set items, the start record)."""
    cfg = _config(name)
    weights, state_file = carry / name / "model.safetensors", carry / name / "lease_state.json"
    calls = json.loads(state_file.read_text())["calls"] if state_file.is_file() else []
    sets, start = [], {"calls_before": len(calls)}
    if weights.is_file():
        sets.append(f"train.init_from={weights}")
        start |= {"from": str(weights), "sha256": sha256(weights), "carried": True}
    else:
        start |= {"from": cfg["train"].get("init_from"), "carried": False}  # None: from scratch
        calls = []
    if not any(o.startswith("train.seed=") for o in overrides):  # a new seed per call: new crops and turbulence
        sets.append(f"train.seed={int(cfg['train'].get('seed', 0)) + SEED_STRIDE * len(calls)}")
    start["previous_calls"] = calls
    return sets, start


def write_lease_state(s: Session, name: str, run: Path) -> None:
    """``run/lease_state.json``: the carried calls, this one appended, and the checksum of the weights it goes with."""
    cand = s.report["candidates"].get(name, {})
    weights = run / "model.safetensors"
    if not weights.is_file():
        return
    start = cand.get("start", {})
    calls = list(start.get("previous_calls", []))
    status = json.loads((run / "status.json").read_text()) if (run / "status.json").is_file() else {}
    import yaml

    resolved = yaml.safe_load((run / "config.yaml").read_text()) if (run / "config.yaml").is_file() else {}
    cfg = resolved.get("train", {})
    last = (cand.get("validation") or {}).get("last") or {}
    iterations = int(status.get("iteration") or 0)
    calls.append(
        {
            "call": len(calls) + 1,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "device": s.report["steps"].get("check", {}).get("gpu", "cpu" if s.rehearsal else None),
            "rehearsal": s.rehearsal,
            "from": start.get("from"),
            "from_sha256": start.get("sha256"),
            "seed": cfg.get("seed"),
            "lr": cfg.get("lr"),
            "batch": cfg.get("batch"),
            "patch": resolved.get("data", {}).get("patch"),
            "iterations": iterations,
            "images": iterations * int(cfg.get("batch") or 0),
            "validation": {k: v for k, v in last.items() if k.startswith("val_")},
        }
    )
    state = {
        "model": name,
        "config": CANDIDATES[name][0],
        "weights_sha256": sha256(weights),
        "iterations_total": sum(c["iterations"] for c in calls),
        "images_total": sum(c["images"] for c in calls),
        "calls": calls,
    }
    tmp = run / ".lease_state.json.tmp"
    tmp.write_text(json.dumps(state, indent=1))
    os.replace(tmp, run / "lease_state.json")


def _tar(target: Path, name: str, members: list[Path]) -> None:
    tmp = target.with_name(f".{target.name}.tmp")
    with tarfile.open(tmp, "w") as tar:
        for m in members:
            tar.add(m, arcname=f"{name}/{m.name}")
    os.replace(tmp, target)


def collect(s: Session, name: str, run: Path) -> None:
    """``NAME.tar``: the final weights (what the next call continues from), lease_state.json and the logs; the best
    weights with them where they differ and fit, else in ``NAME_best.tar`` while the 8 files that come back allow."""
    write_lease_state(s, name, run)
    files = ("model.safetensors", "lease_state.json", "log.jsonl", "status.json", "config.yaml", "train.log")
    members = [run / f for f in files if (run / f).is_file()]
    best, final = run / "best.safetensors", run / "model.safetensors"
    same = final.is_file() and best.is_file() and _tensors_sha256(best) == _tensors_sha256(final) is not None
    if best.is_file() and not same:
        if sum(m.stat().st_size for m in members) + best.stat().st_size < TAR_LIMIT:
            members.append(best)
        elif len([p for p in s.out.iterdir() if p.is_file()]) + 2 <= MAX_FILES:
            _tar(s.out / f"{name}_best.tar", name, [best])
            s.log(f"collect: {name}_best.tar ({best.stat().st_size / 2**20:.1f} MiB)")
        else:
            s.log(f"collect: {name}'s best.safetensors left out (no file of the {MAX_FILES} left)")
    if not members:
        return
    target = s.out / f"{name}.tar"
    _tar(target, name, members)
    if target.stat().st_size > TAR_LIMIT:  # never here for the shipped candidates (≤ 2.6 M parameters)
        s.log(f"collect: {target.name} is over 15 MiB and will not come back")
    s.log(f"collect: {target.name} ({target.stat().st_size / 2**20:.1f} MiB: {', '.join(m.name for m in members)})")


def unpack(came_back: Path, carry: Path, force: bool) -> int:
    """Here, after a call: each ``NAME.tar`` in ``came_back`` → ``carry/NAME/{model.safetensors, lease_state.json}``,
    checked (the weights' checksum is the state's) and refused where it does not continue the state already there
    (its calls must start with the carried ones; ``force`` replaces it anyway)."""
    tars = sorted(p for p in came_back.glob("*.tar") if not p.name.endswith("_best.tar"))
    if not tars:
        print(f"error: no NAME.tar in {came_back}", file=sys.stderr)
        return 2
    for path in tars:
        name = path.stem
        with tarfile.open(path) as tar:
            try:
                weights = tar.extractfile(f"{name}/model.safetensors").read()
                state = json.loads(tar.extractfile(f"{name}/lease_state.json").read())
            except (KeyError, AttributeError):
                print(f"error: {path} has no {name}/model.safetensors and lease_state.json", file=sys.stderr)
                return 2
        if hashlib.sha256(weights).hexdigest() != state["weights_sha256"]:
            print(f"error: {path}: the weights are not the ones lease_state.json names", file=sys.stderr)
            return 2
        target = carry / name
        old = target / "lease_state.json"
        if old.is_file() and not force:
            before = json.loads(old.read_text())["calls"]
            if state["calls"][: len(before)] != before or len(state["calls"]) <= len(before):
                print(
                    f"error: {path} does not continue {old} ({len(state['calls'])} calls against {len(before)} "
                    "carried); --force replaces it",
                    file=sys.stderr,
                )
                return 2
        target.mkdir(parents=True, exist_ok=True)
        for file, data in (("model.safetensors", weights), ("lease_state.json", json.dumps(state, indent=1).encode())):
            tmp = target / f".{file}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, target / file)
        last = state["calls"][-1]
        print(
            f"{name}: call {last['call']} unpacked into {target} ({state['iterations_total']} iterations, "
            f"{state['images_total']} images in all); carry {carry} into the next call"
        )
    return 0


def carry_size(paths: list[str]) -> int:
    """The bytes a call carries: the checkout's tracked and untracked-but-not-ignored files, plus ``paths``."""
    out = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout
    files = {ROOT / f.decode() for f in out.split(b"\0") if f}
    for p in paths:
        p = ROOT / p
        files |= {f for f in p.rglob("*")} if p.is_dir() else {p}
    return sum(f.stat().st_size for f in files if f.is_file() and not f.is_symlink())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="the folder that comes back ($OUT on the device)")
    ap.add_argument("--pack", default=None, help="training pack (default packs/clean, carried; built when missing)")
    ap.add_argument("--clean", default=None, help="clean images to build the pack from when it is missing")
    ap.add_argument("--runs", default="runs/lease", help="run folders (not brought back whole)")
    ap.add_argument(
        "--candidates",
        default=DEFAULT_CANDIDATES,
        help=f"comma-separated names of {', '.join(CANDIDATES)} (default {DEFAULT_CANDIDATES}); side by side they "
        "share the device (docs/training.md)",
    )
    ap.add_argument("--carry", default=CARRY, help=f"the carried state of previous calls (default {CARRY})")
    ap.add_argument("--unpack", metavar="DIR", help="here, after a call: DIR's NAME.tar → --carry, then exit")
    ap.add_argument("--force", action="store_true", help="--unpack: replace a carried state it does not continue")
    ap.add_argument(
        "--carry-size", nargs="*", metavar="PATH", help="print the MiB a call carrying PATHs would take, then exit"
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
    carry = (ROOT / args.carry).resolve()
    if args.unpack:
        return unpack(Path(args.unpack), carry, args.force)
    if args.carry_size is not None:
        total = carry_size(args.carry_size)
        fits = total <= CARRY_LIMIT
        print(f"{total / 2**20:.1f} MiB of {CARRY_LIMIT / 2**20:.0f}: {'fits' if fits else 'over the limit'}")
        return 0 if fits else 1
    if not args.out:
        print("error: --out is required (the folder that comes back)", file=sys.stderr)
        return 2
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
            start_sets, start = start_state(n, carry, args.overrides)
            minutes = (end_train_s - s.elapsed() - (5 if s.rehearsal else 30)) / 60  # start-up: imports, pack decode
            batch = 2 if s.rehearsal else cfg["train"]["batch"]
            planned = max(1, int(rates[n]["images_per_s"] * 60 * minutes * SAFETY / batch))
            if s.rehearsal:
                planned = min(planned, 4)
            sets = [f"train.iterations={planned}", f"train.max_minutes={max(minutes, 0.05):.3f}"]
            sets += [f"data.pack={pack}", f"val.pack={pack}"]
            sets += start_sets + args.overrides
            if s.rehearsal:
                sets += REHEARSAL_SET
            elif rates[n].get("fallback_float32"):
                sets += ["train.amp=null", "train.channels_last=false"]
            jobs[n] = [sys.executable, "-m", "d2turb", "train", "--config", str(ROOT / CANDIDATES[n][0])]
            jobs[n] += ["--out", str(runs / n)] + [a for kv in sets for a in ("--set", kv)]
            logs[n] = runs / n / "train.log"
            s.report["candidates"][n] = {
                "planned_iterations": planned,
                "minutes": round(minutes, 2),
                "set": sets,
                "start": start,
            }
            origin = f"carried call {start['calls_before']}" if start["carried"] else start["from"] or "scratch"
            s.log(f"train {n}: {planned} iterations in ≤ {minutes:.2f} min, from {origin}")
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
