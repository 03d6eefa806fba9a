"""`d2turb train`: train a model from a YAML config (single process, or DDP under torchrun); `--detach` runs it
in the background, `--status RUN_DIR` reports its progress."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
import warnings

from d2turb.commands.common import log_to_stderr
from d2turb.errors import D2TurbError


def register(sub):
    p = sub.add_parser(
        "train",
        help="train a restoration model from a YAML config",
        description="Train from a YAML config (see configs/ and docs/training.md). Multi-GPU: "
        "torchrun --nproc_per_node N -m d2turb train ... (total batch split across processes). "
        "An existing RUN_DIR/last.pt is resumed automatically. SIGTERM (and train.max_minutes) checkpoint "
        "and exit cleanly.",
    )
    p.add_argument("--config", metavar="YAML", help="training config file")
    p.add_argument("--out", metavar="RUN_DIR", help="run folder (default: runs/<config name>)")
    p.add_argument("--resume", action="store_true", help="require RUN_DIR/last.pt and continue from it")
    p.add_argument(
        "--init-from",
        metavar="NAME|FILE",
        help="start from these weights (a d2turb .safetensors or a weights name; weights only, config must match; "
        "ignored when RUN_DIR/last.pt exists)",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set train.iterations=100 (repeatable; value parsed as YAML)",
    )
    p.add_argument(
        "--detach",
        action="store_true",
        help="run in the background (new session; output to RUN_DIR/train.log) and return at once",
    )
    p.add_argument("--status", metavar="RUN_DIR", help="print the progress of the run in RUN_DIR and exit")
    p.set_defaults(func=run, _parser=p)


def _config_and_out(args):
    # lazy: see d2turb.commands
    from d2turb.train import load_config

    if not args.config:
        raise D2TurbError("train: --config is required (or --status RUN_DIR)")
    cfg = load_config(args.config, args.overrides)
    if args.init_from:
        cfg.train.init_from = args.init_from
    out = args.out or os.path.join("runs", os.path.splitext(os.path.basename(args.config))[0])
    return cfg, out


def _refuse_if_running(out: str) -> None:
    # lazy: see d2turb.commands
    from d2turb.train.status import STATUS, read_status

    if os.path.isfile(os.path.join(out, STATUS)):
        status = read_status(out)
        if status.get("alive"):
            raise D2TurbError(f"{out} is being trained by process {status['pid']}; see `d2turb train --status {out}`")


def _child_argv(args) -> list[str]:
    """This command's arguments without --detach, rebuilt from the parsed values."""
    argv = ["train"]
    for action in args._parser._actions:
        if not action.option_strings or action.dest in ("help", "detach", "status", "out"):
            continue
        value, flag = getattr(args, action.dest, None), action.option_strings[-1]
        if action.nargs == 0:
            argv += [flag] if value else []
        elif isinstance(value, list):
            for item in value:
                argv += [flag, str(item)]
        elif value is not None and value != action.default:
            argv += [flag, str(value)]
    return argv


def _detach(args, out: str) -> int:
    os.makedirs(out, exist_ok=True)
    logfile = os.path.join(out, "train.log")
    with open(logfile, "ab") as f:
        proc = subprocess.Popen(
            [sys.executable, "-m", "d2turb", *_child_argv(args), "--out", out],
            stdin=subprocess.DEVNULL,
            stdout=f,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    print(f"training in the background: pid {proc.pid}, log {logfile}; progress: d2turb train --status {out}")
    return 0


def _hms(seconds) -> str:
    if seconds is None:
        return "?"
    seconds = int(seconds)
    return f"{seconds // 3600:d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def print_status(run_dir: str) -> int:
    # lazy: see d2turb.commands
    from d2turb.train.status import read_status

    s = read_status(run_dir)
    state = s["state"]
    if state == "running":
        state += {True: f" (pid {s['pid']}, alive)", False: f" (pid {s['pid']} is gone: killed?)"}.get(
            s["alive"], f" (pid {s['pid']} on {s.get('host')})"
        )
    elif s.get("reason"):
        state += f" ({s['reason']})"
    if s.get("error"):
        state += f": {s['error']}"
    rate = f"{s['it_per_s']:.2f} it/s" if s.get("it_per_s") else "? it/s"
    pct = 100.0 * s["iteration"] / max(1, s["total"])
    lines = [
        f"run {run_dir}: {state}; updated {_hms(time.time() - s['updated'])} ago",
        f"iteration {s['iteration']}/{s['total']} ({pct:.1f} %), {rate}, elapsed {_hms(s.get('elapsed_s'))}, "
        f"ETA {_hms(s.get('eta_s'))}, last checkpoint at {s.get('checkpoint_iteration')}",
    ]
    if s.get("loss") is not None:
        lines.append(f"loss {s['loss']:.5f}")
    val = s.get("val")
    if val:
        text = f"val (iteration {val['iter']}): PSNR {val['psnr']:.3f} dB, SSIM {val['ssim']:.4f}"
        if "psnr_input" in val:
            text += f" (input {val['psnr_input']:.3f} dB, {val['ssim_input']:.4f})"
        if "epe" in val:
            text += f"; flow EPE {val['epe']:.3f} px (zero flow {val['epe_zero']:.3f} px)"
        lines.append(text)
    print("\n".join(lines))
    return 0


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"warning: {message}", file=sys.stderr)


def run(args):
    if args.status:
        return print_status(args.status)
    cfg, out = _config_and_out(args)
    _refuse_if_running(out)
    if args.detach:
        return _detach(args, out)
    # lazy: see d2turb.commands
    from d2turb.train import Trainer

    log_to_stderr({"d2turb.train": logging.INFO})
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning  # one line per warning: "warning: ..."
        trainer = Trainer(cfg, out, resume=args.resume)
        try:
            summary = trainer.fit(handle_sigterm=True)
        except BaseException as exc:
            trainer.write_status("failed", error=f"{exc.__class__.__name__}: {exc}"[:500])
            raise
        finally:
            trainer.close()
    if trainer.is_main:
        best = f", best val PSNR {summary['best_psnr']:.3f} dB" if summary["best_psnr"] > -float("inf") else ""
        stopped = "" if summary["stopped"] == "done" else f" (stopped: {summary['stopped']}; rerun to resume)"
        print(
            f"trained {summary['iteration']}/{summary['total']} iterations, last loss {summary['loss']:.5f}{best}; "
            f"wrote {out}{stopped}"
        )
    return 0
