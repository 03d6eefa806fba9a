"""Training loop (Sec. 3.3 / Sec. 4.1): Adam, cosine annealing lr → lr_min over the run, total batch split across
DDP processes, validation (PSNR/SSIM, flow end-point error), JSON-lines log, atomic resumable checkpoints, an EMA
of the weights, bf16 autocast / channels_last / torch.compile options and a time budget for short GPU jobs.

Run folder: ``last.pt`` (resume state: model, EMA, optimiser, scheduler, iteration, per-rank RNG states, config;
loaded with ``torch.load(weights_only=True)``), ``model.safetensors`` / ``best.safetensors`` (``save_pretrained``;
the EMA weights when ``train.ema`` is set), ``log.jsonl``, ``status.json`` (progress, for ``d2turb train
--status``), ``config.yaml``. Only rank 0 writes. Resuming is exact with ``num_workers: 0``: the data order is a
function of (seed, epoch), the batches already consumed in the current epoch are skipped, and all RNG states
return. The trainer never seeds the process-wide RNG: it draws from its own generators and, while it trains,
swaps its own CPU/CUDA RNG state in (``torch.random.fork_rng``) so that dataset augmentations that use the global
RNG stay reproducible, and the caller's state comes back afterwards.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import socket
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import nullcontext
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, DistributedSampler, Sampler, Subset

from d2turb.data import CleanCropDataset, OnTheFlySynthesis, PairDataset, crop_sample
from d2turb.data.layout import BIN_NAMES
from d2turb.data.pack import PackCrops
from d2turb.data.split import split_of
from d2turb.device import resolve_device
from d2turb.errors import D2TurbError
from d2turb.eval.metrics import end_point_error, psnr, ssim
from d2turb.io import atomic_path, remove_stale_temp_files, write_json, write_text
from d2turb.models import create_model, load_pretrained, save_pretrained
from d2turb.models.hub import IDENTITY_NAME, resolve_weights
from d2turb.sim import Simulator
from d2turb.sim.geometry import geometry_bank
from d2turb.train.config import Config, model_kwargs
from d2turb.train.ema import EMA
from d2turb.train.losses import build_loss

CHECKPOINT = "last.pt"
STATUS = "status.json"
FORMAT = 1
_EMPTY = torch.zeros(0, dtype=torch.uint8)
_AUG_SEED_STRIDE = 7919  # per-rank offset of the trainer's own RNG streams
log = logging.getLogger("d2turb.train")


class ResumableSampler(Sampler):
    """A DistributedSampler (shuffled by seed + epoch, rank's share) that can skip its first ``skip`` indices."""

    def __init__(self, dataset, world: int, rank: int, seed: int, shuffle: bool = True):
        self.inner = DistributedSampler(dataset, num_replicas=world, rank=rank, shuffle=shuffle, seed=seed)
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        self.inner.set_epoch(epoch)
        self.skip = skip

    def __iter__(self):
        return iter(list(self.inner)[self.skip :])

    def __len__(self) -> int:
        return len(self.inner) - self.skip


def _env_int(name: str, default: int) -> int:
    try:
        return int(os.environ.get(name, default))
    except ValueError as exc:
        raise D2TurbError(f"environment variable {name} must be an integer, got {os.environ[name]!r}") from exc


def init_distributed(device_name: str) -> tuple[int, int, torch.device]:
    """(rank, world_size, device) from torchrun's RANK / WORLD_SIZE / LOCAL_RANK; nccl on CUDA, gloo on CPU."""
    world, rank, local = _env_int("WORLD_SIZE", 1), _env_int("RANK", 0), _env_int("LOCAL_RANK", 0)
    device = resolve_device(device_name, local)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=rank, world_size=world)
    return rank, world, device


def _gather(obj, world: int) -> list:
    if world == 1:
        return [obj]
    out = [None] * world
    dist.all_gather_object(out, obj)
    return out


def read_status(run_dir: str | os.PathLike) -> dict:
    """The ``status.json`` of a run folder, with ``alive`` added (True/False for a running process on this host,
    None when it cannot be told)."""
    path = Path(run_dir) / STATUS
    if not path.is_file():
        raise D2TurbError(f"{run_dir}: no {STATUS} (not a run folder, or training has not started yet)")
    try:
        status = json.loads(path.read_text())
    except ValueError as exc:
        raise D2TurbError(f"{path}: unreadable") from exc
    status["alive"] = None
    if status.get("state") == "running" and status.get("host") == socket.gethostname():
        try:
            os.kill(int(status["pid"]), 0)
            status["alive"] = True
        except ProcessLookupError:
            status["alive"] = False
        except (PermissionError, KeyError, ValueError, TypeError):
            pass
    return status


class _Sums:
    """Per-key sums and counts of per-image values, all-reduced across ranks in one collective."""

    def __init__(self) -> None:
        self.sums: dict[str, list[float]] = {}

    def add(self, key: str, values: torch.Tensor) -> None:
        s = self.sums.setdefault(key, [0.0, 0.0])
        values = values.detach().double().cpu()
        s[0] += float(values.sum())
        s[1] += values.numel()

    def means(self, keys: list[str], world: int, device: torch.device) -> dict[str, float]:
        table = torch.tensor([self.sums.get(k, [0.0, 0.0]) for k in keys], dtype=torch.float64)
        if world > 1:
            table = table.to(device)
            dist.all_reduce(table, op=dist.ReduceOp.SUM)
            table = table.cpu()
        return {k: (s / n if n else math.nan) for k, (s, n) in zip(keys, table.tolist())}


class Trainer:
    """``Trainer(cfg, run_dir).fit()``.

    Args:
        cfg: a :class:`d2turb.train.config.Config` (or a mapping, validated with ``Config.from_dict``).
        run_dir: the run folder; an existing ``last.pt`` there is resumed.
        resume: require ``run_dir/last.pt``.
        progress: show a progress bar (default: ``cfg.log.progress``).
    """

    def __init__(
        self, cfg: Config | dict, run_dir: str | os.PathLike, resume: bool = False, progress: bool | None = None
    ):
        self.cfg = cfg if isinstance(cfg, Config) else Config.from_dict(cfg)
        self.run_dir = Path(run_dir)
        self.progress = self.cfg.log.progress if progress is None else progress
        self._clock0 = time.monotonic()  # the time budget counts from here (data decoding included)
        self._stop_requested = self._handles_signal = False
        self._check_resume(resume)
        self._setup_process()
        self._build_model()
        self._build_loss_and_optimizer()
        self._build_data()
        self._build_schedule_and_loader()
        self._build_validation()
        self._wrap_model()
        self._restore_or_init()

    # ---------------------------------------------------------------- construction steps
    def _check_resume(self, resume: bool) -> None:
        self.checkpoint_path = self.run_dir / CHECKPOINT
        if _env_int("RANK", 0) == 0:  # temp checkpoints (hundreds of MB) of a killed run, before anything is written
            remove_stale_temp_files(self.run_dir)
        self.resuming = self.checkpoint_path.is_file()
        if resume and not self.resuming:
            raise D2TurbError(f"--resume: no checkpoint {self.checkpoint_path}")

    def _setup_process(self) -> None:
        """Rank, world size, device, per-process batch, and the trainer's own RNG streams."""
        tcfg = self.cfg.train
        self.rank, self.world, self.device = init_distributed(tcfg.device)
        self.is_main = self.rank == 0
        if tcfg.batch % self.world:
            raise D2TurbError(f"train.batch {tcfg.batch} is not divisible by the {self.world} processes")
        self.per_rank_batch = tcfg.batch // self.world
        if tcfg.amp == "bf16" and self.device.type not in ("cuda", "cpu"):
            raise D2TurbError(f"train.amp bf16 is not supported on {self.device.type}")
        stream = tcfg.seed + _AUG_SEED_STRIDE * self.rank  # per-rank augmentation stream
        self._rng_cpu = torch.Generator().manual_seed(stream).get_state()
        self._rng_cuda = (
            torch.Generator(device=self.device).manual_seed(stream).get_state()
            if self.device.type == "cuda"
            else _EMPTY
        )
        self._rng_live = False

    def _build_model(self) -> None:
        """The model, created from ``train.seed`` (identical on every rank) without touching the global RNG."""
        name, kwargs = model_kwargs(self.cfg)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.cfg.train.seed)
            model = create_model(name, **kwargs)
        self.model = model.to(self.device).train()
        if self.cfg.train.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)

    def _build_loss_and_optimizer(self) -> None:
        tcfg = self.cfg.train
        self.loss = build_loss(dict(vars(self.cfg.loss)), self.model, self.device, warn=self.is_main)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=tcfg.lr, betas=tuple(tcfg.betas), weight_decay=tcfg.weight_decay
        )

    def _make_synthesis(self, bins, seed: int):
        """On-the-fly synthesis on the training device (one place, for training and pack validation)."""
        otf = self.cfg.data.on_the_fly
        if getattr(self, "_simulators", None) is None:
            self._simulators = [Simulator(p, self.device) for p in geometry_bank(otf.geometry, otf.params or {})]
        return OnTheFlySynthesis(
            self._simulators, bins=tuple(bins), device=self.device, seed=seed, use_depth=otf.depth != "none"
        )

    def _build_data(self) -> None:
        """``self.dataset`` (CPU items, or device items for a pack) and ``self.synthesis`` (None for pairs)."""
        data, seed = self.cfg.data, self.cfg.train.seed
        self.synthesis = None
        if data.source == "pairs":
            probe = PairDataset(data.pairs)
            self.dataset = PairDataset(
                data.pairs, crop=min(data.patch, probe.patch), hflip=data.hflip, vflip=data.vflip
            )
            return
        otf = data.on_the_fly
        if data.source == "clean":
            tests = sorted({Path(c).name for c in data.clean if split_of(c) == "test"})
            if tests and self.is_main:
                warnings.warn(
                    f"data.clean includes test folder(s) {', '.join(tests)} of the fixed split (d2turb.data.split)",
                    stacklevel=2,
                )
            self.dataset = CleanCropDataset(
                data.clean, patch=data.patch, depth_spec=otf.depth, length=otf.length, hflip=data.hflip
            )
        else:
            self.dataset = PackCrops(
                data.pack,
                patch=data.patch,
                split="train",
                length=otf.length,
                hflip=data.hflip,
                vflip=data.vflip,
                depth=otf.depth,
                device=self.device,
                seed=seed + _AUG_SEED_STRIDE * self.rank,
            )
        self.synthesis = self._make_synthesis(otf.bins, seed + self.rank)

    def _build_schedule_and_loader(self) -> None:
        tcfg, data = self.cfg.train, self.cfg.data
        self.sampler = ResumableSampler(self.dataset, self.world, self.rank, tcfg.seed)
        self.iters_per_epoch = len(self.sampler) // self.per_rank_batch
        if self.iters_per_epoch < 1:
            raise D2TurbError(
                f"the training set has {len(self.dataset)} samples, fewer than one batch of "
                f"{self.per_rank_batch} per process"
            )
        self.total = tcfg.iterations or tcfg.epochs * self.iters_per_epoch
        self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            self.optimizer, T_max=self.total, eta_min=tcfg.lr_min
        )
        self.loader_generator = torch.Generator().manual_seed(tcfg.seed + self.rank)
        in_memory = data.source == "pack"  # device tensors: no workers, no pinning
        self.loader = DataLoader(
            self.dataset,
            batch_size=self.per_rank_batch,
            sampler=self.sampler,
            drop_last=True,
            num_workers=0 if in_memory else data.num_workers,
            generator=self.loader_generator,
            pin_memory=self.device.type == "cuda" and not in_memory,
        )

    def _build_validation(self) -> None:
        """``self.val_loader``: an iterable of batches (CPU pairs from ``val.pairs``, or device batches synthesised
        once from a pack's val images), this rank's share; None without validation."""
        val = self.cfg.val
        self.val_loader = None
        if val.pairs is not None:
            dataset = PairDataset(val.pairs)
            n = len(dataset) if val.max_images is None else min(len(dataset), val.max_images)
            shard = Subset(dataset, list(range(self.rank, n, self.world)))
            self.val_loader = DataLoader(shard, batch_size=val.batch, shuffle=False, num_workers=0)
        elif val.pack is not None:
            self.val_loader = self._pack_validation()

    def _pack_validation(self) -> list[dict]:
        """One centre crop per val image × one pair per bin, each from its own seed (so the set does not depend
        on the number of processes); this rank's share, batched by ``val.batch``."""
        val, otf = self.cfg.val, self.cfg.data.on_the_fly
        size = val.crop or self.cfg.data.patch
        crops = PackCrops(val.pack, patch=size, split="val", depth=otf.depth, device=self.device).center_crops(size)
        if val.max_images is not None:
            crops = crops[: val.max_images]
        pairs = []
        for k, crop in enumerate(crops):
            for j, b in enumerate(otf.bins):
                if (k * len(otf.bins) + j) % self.world != self.rank:
                    continue
                synth = self._make_synthesis([b], seed=val.seed + 1009 * k + j)
                batch = {"gt": crop["gt"][None], "depth": crop["depth"][None], "id": [crop["id"]]}
                out = synth(batch)
                pairs.append({key: out[key] for key in ("turb", "gt", "bwd_flow_px", "bin")})
        return [
            {key: torch.cat([p[key] for p in pairs[i : i + val.batch]]) for key in pairs[0]}
            for i in range(0, len(pairs), val.batch)
        ]

    def _wrap_model(self) -> None:
        """EMA copy, DDP wrapper and torch.compile of the forward (``self.forward``)."""
        tcfg = self.cfg.train
        self.ema = EMA(self.model, tcfg.ema) if tcfg.ema is not None else None
        self.ddp = self.model
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel

            self.ddp = DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None
            )
        self.forward = self.ddp
        if tcfg.compile:
            backend = "inductor" if tcfg.compile is True else tcfg.compile
            self.forward = torch.compile(self.ddp, backend=backend)

    def _restore_or_init(self) -> None:
        self.iteration, self.best_psnr = 0, -math.inf
        if self.resuming:
            self.load_checkpoint(self.checkpoint_path)
            if self.cfg.train.init_from and self.is_main:
                log.info("resuming %s at iteration %d; train.init_from ignored", self.run_dir, self.iteration)
        elif self.cfg.train.init_from:
            self.init_from(self.cfg.train.init_from)

    # ---------------------------------------------------------------- weights in
    def init_from(self, weights: str | os.PathLike) -> None:
        """Load weights only (no optimiser or schedule) from a d2turb ``.safetensors`` file or weights name
        (resolved like ``d2turb restore --weights``); its model config must equal this run's, loading is strict.
        The EMA restarts from these weights."""
        path = resolve_weights(weights)
        if path == IDENTITY_NAME:
            raise D2TurbError(f"--init-from {weights}: not a weights file")
        source = load_pretrained(path)  # verifies the checksum, strict
        if _jsonable(source.config) != _jsonable(self.model.config):
            raise D2TurbError(
                f"--init-from {path}: the weights are for model {_jsonable(source.config)}, "
                f"not {_jsonable(self.model.config)}"
            )
        self.model.load_state_dict(source.state_dict(), strict=True)
        if self.ema is not None:
            self.ema = EMA(self.model, self.cfg.train.ema)
        if self.is_main:
            log.info("initialised from %s", path)

    # ---------------------------------------------------------------- state
    @contextlib.contextmanager
    def _own_rng(self) -> Iterator[None]:
        """Swap the trainer's CPU (and CUDA) RNG state in for the block; the caller's comes back afterwards."""
        cuda = self.device.type == "cuda"
        with torch.random.fork_rng(devices=[self.device] if cuda else [], device_type="cuda"):
            torch.set_rng_state(self._rng_cpu)
            if cuda:
                torch.cuda.set_rng_state(self._rng_cuda, self.device)
            self._rng_live = True
            try:
                yield
            finally:
                self._rng_live = False
                self._rng_cpu = torch.get_rng_state()
                if cuda:
                    self._rng_cuda = torch.cuda.get_rng_state(self.device)

    def _rng_state(self) -> dict:
        live = self._rng_live
        cpu = torch.get_rng_state() if live else self._rng_cpu
        cuda = torch.cuda.get_rng_state(self.device) if live and self.device.type == "cuda" else self._rng_cuda
        data = getattr(self.dataset, "generator", None)
        return {
            "cpu": cpu,
            "cuda": cuda.cpu(),
            "synth": self.synthesis.generator.get_state().cpu() if self.synthesis is not None else _EMPTY,
            "loader": self.loader_generator.get_state(),
            "data": data.get_state() if isinstance(data, torch.Generator) else _EMPTY,
        }

    def _set_rng_state(self, state: dict) -> None:
        self._rng_cpu = state["cpu"]
        if self.device.type == "cuda" and state["cuda"].numel():
            self._rng_cuda = state["cuda"]
        if self.synthesis is not None and state["synth"].numel():
            self.synthesis.generator.set_state(state["synth"])
        self.loader_generator.set_state(state["loader"])
        data = getattr(self.dataset, "generator", None)
        if isinstance(data, torch.Generator) and state.get("data", _EMPTY).numel():
            data.set_state(state["data"])

    def save_checkpoint(self) -> Path | None:
        """Atomically write ``last.pt`` (rank 0; every rank contributes its RNG state)."""
        rngs = _gather(self._rng_state(), self.world)
        if not self.is_main:
            return None
        state = {
            "format": FORMAT,
            "iteration": self.iteration,
            "world_size": self.world,
            "best_psnr": self.best_psnr,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "rng": rngs,
            "config": json.dumps(self.cfg.to_dict()),
        }
        if self.ema is not None:
            state["ema"] = self.ema.state_dict()
        with atomic_path(self.checkpoint_path) as tmp:
            torch.save(state, tmp)
        self._checkpoint_iteration = self.iteration
        return self.checkpoint_path

    def load_checkpoint(self, path: Path) -> None:
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            saved_cfg = json.loads(state["config"])
        except Exception as exc:  # truncated file, foreign pickle, missing keys
            raise D2TurbError(f"{path}: unreadable checkpoint ({exc.__class__.__name__})") from exc
        if saved_cfg.get("model") != self.cfg.model:
            raise D2TurbError(
                f"{path}: checkpoint is for model {saved_cfg.get('model')}, not {self.cfg.model}; "
                "use another --out folder"
            )
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.iteration, self.best_psnr = int(state["iteration"]), float(state["best_psnr"])
        self._checkpoint_iteration = self.iteration
        if self.is_main:
            self._truncate_log(self.iteration)
        if self.ema is not None:
            if "ema" in state:
                self.ema.load_state_dict(state["ema"])
            else:
                self.ema = EMA(self.model, self.cfg.train.ema)
                if self.is_main:
                    warnings.warn(f"{path} has no EMA weights; the EMA starts from the current weights", stacklevel=2)
        if state["world_size"] == self.world:
            self._set_rng_state(state["rng"][self.rank])
        elif self.is_main:
            warnings.warn(
                f"resuming a {state['world_size']}-process run on {self.world}; data order and RNG streams restart",
                stacklevel=2,
            )

    @property
    def eval_model(self) -> torch.nn.Module:
        """The weights that validate and ship: the EMA when ``train.ema`` is set, else the trained model."""
        return self.ema.model if self.ema is not None else self.model

    def _truncate_log(self, iteration: int) -> None:
        """Drop the ``log.jsonl`` lines of iterations after ``iteration`` (those a killed run logged after its last
        checkpoint: the resumed run trains them again), atomically."""
        path = self.run_dir / "log.jsonl"
        try:
            lines = path.read_text().splitlines(keepends=True)
        except FileNotFoundError:
            return
        except (OSError, UnicodeDecodeError) as exc:
            raise D2TurbError(f"{path}: cannot read ({exc.__class__.__name__}: {exc})") from exc

        def kept(line: str) -> bool:
            try:
                record = json.loads(line)
            except ValueError:
                return False  # a line cut by the kill
            return not (isinstance(record, dict) and isinstance(record.get("iter"), int) and record["iter"] > iteration)

        keep = [line for line in lines if kept(line)]
        if keep != lines:
            write_text(path, "".join(line if line.endswith("\n") else line + "\n" for line in keep))

    def _log(self, record: dict) -> None:
        if self.is_main:
            with open(self.run_dir / "log.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")

    def _save_weights(self, name: str) -> None:
        if self.is_main:
            save_pretrained(self.eval_model, self.run_dir / name)

    def write_status(self, state: str, **extra) -> None:
        """Write ``status.json`` (rank 0): state, pid, progress, speed, ETA, last loss and validation."""
        if not self.is_main:
            return
        now = time.monotonic()
        run_s = now - getattr(self, "_fit_clock", now)
        done = self.iteration - getattr(self, "_fit_start_iter", self.iteration)
        rate = done / run_s if run_s > 0 and done > 0 else None
        status = {
            "state": state,
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "run_dir": str(self.run_dir),
            "iteration": self.iteration,
            "total": self.total,
            "it_per_s": rate,
            "eta_s": (self.total - self.iteration) / rate if rate else None,
            "elapsed_s": round(now - self._clock0, 1),
            "max_minutes": self.cfg.train.max_minutes,
            "updated": time.time(),
            "loss": getattr(self, "_last_loss", None),
            "val": getattr(self, "_last_val", None),
            "checkpoint_iteration": getattr(self, "_checkpoint_iteration", None),
            **extra,
        }
        self.run_dir.mkdir(parents=True, exist_ok=True)
        write_json(self.run_dir / STATUS, status)
        self._status_written = now

    # ---------------------------------------------------------------- steps
    def _autocast(self):
        if self.cfg.train.amp == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return nullcontext()

    def _input(self, image: torch.Tensor) -> torch.Tensor:
        image = image.to(self.device, non_blocking=True)
        return image.contiguous(memory_format=torch.channels_last) if self.cfg.train.channels_last else image

    def _to_device(self, batch: dict) -> dict:
        if self.synthesis is not None:
            return self.synthesis(batch)
        return {k: v.to(self.device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}

    def train_step(self, batch: dict) -> tuple[float, dict]:
        """One optimiser step on a device batch (turb, tilt, gt, flow); returns (loss, unweighted terms)."""
        with self._autocast():
            out = self.forward(self._input(batch["turb"]))
        loss, terms = self.loss(out, batch)
        self._check_finite(loss)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        clip = self.cfg.train.grad_clip
        if clip:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), float(clip))
        self.optimizer.step()
        self.scheduler.step()
        if self.ema is not None:
            self.ema.update(self.model)
        return float(loss.detach()), terms

    def _check_finite(self, loss: torch.Tensor) -> None:
        """Stop before the backward pass of an inf/NaN loss (agreed by all ranks): a NaN flow reaching
        ``grid_sample``'s backward crashes the process (SIGSEGV on the CPU), and the step would spoil the weights."""
        finite = torch.isfinite(loss.detach()).float().reshape(1)
        if self.world > 1:
            backend_device = self.device if dist.get_backend() == "nccl" else torch.device("cpu")
            finite = finite.to(backend_device)
            dist.all_reduce(finite, op=dist.ReduceOp.MIN)
        if finite.item() == 0:
            tcfg = self.cfg.train
            raise D2TurbError(
                f"loss became non-finite at iteration {self.iteration + 1} ({float(loss.detach())} on rank "
                f"{self.rank}): training diverged; lower train.lr (now {tcfg.lr}) or set train.grad_clip "
                f"(now {tcfg.grad_clip}); the last checkpoint is kept"
            )

    @torch.no_grad()
    def validate(self) -> dict:
        """Mean metrics of the evaluation weights (:attr:`eval_model`) on the validation set, over all ranks:
        ``psnr``, ``ssim`` of ``restored`` (clamped to [0, 1]) and of the input (``psnr_input``, ``ssim_input``),
        the flow end-point error ``epe`` (px, mean over pixels of ‖V̂ − V‖₂) and that of zero flow ``epe_zero``
        (mean ‖V‖₂); the same per bin as ``<metric>_<bin>``."""
        if self.val_loader is None:
            raise D2TurbError("no validation set: set val.pairs or val.pack")
        crop = self.cfg.val.crop if self.cfg.val.pairs is not None else None
        model = self.eval_model
        was_training = model.training
        model.eval()
        sums = _Sums()
        for batch in self.val_loader:
            if crop:
                h, w = batch["gt"].shape[-2:]
                size = min(crop, h, w)
                batch = crop_sample(batch, (h - size) // 2, (w - size) // 2, size)  # deterministic centre crop
            with self._autocast():
                out = model(self._input(batch["turb"]))
            gt, turb = batch["gt"].to(self.device).float(), batch["turb"].to(self.device).float()
            values = {
                "psnr": psnr(out["restored"].float().clamp(0, 1), gt),
                "ssim": ssim(out["restored"].float().clamp(0, 1), gt),
                "psnr_input": psnr(turb, gt),
                "ssim_input": ssim(turb, gt),
            }
            flow = batch.get("bwd_flow_px")
            if out.get("bwd_flow_px") is not None and flow is not None:
                flow = flow.to(self.device).float()
                values["epe"] = end_point_error(out["bwd_flow_px"].float(), flow)
                values["epe_zero"] = end_point_error(flow)
            bins = batch.get("bin")
            for key, v in values.items():
                sums.add(key, v)
                if bins is not None:
                    for i, name in enumerate(BIN_NAMES):
                        chosen = (bins.to(v.device) == i).reshape(-1)
                        if chosen.any():
                            sums.add(f"{key}_{name}", v[chosen])
        model.train(was_training)
        metrics = ("psnr", "ssim", "psnr_input", "ssim_input", "epe", "epe_zero")
        keys = list(metrics) + [f"{m}_{b}" for m in metrics for b in BIN_NAMES]
        means = sums.means(keys, self.world, self.device)
        return {k: v for k, v in means.items() if not math.isnan(v)}

    def _validate_and_save(self, it: int) -> None:
        metrics = self.validate()
        self._last_val = {"iter": it, **metrics}
        self._log({"iter": it, **{f"val_{k}": v for k, v in metrics.items()}, "ema": self.ema is not None})
        self._save_weights("model.safetensors")
        if metrics.get("psnr", -math.inf) > self.best_psnr:
            self.best_psnr = metrics["psnr"]
            self._save_weights("best.safetensors")

    def _after_step(self, record: dict) -> None:
        it, final = self.iteration, self.iteration >= self.total
        if it % self.cfg.log.every == 0 or final:
            self._log(record)
            if time.monotonic() - getattr(self, "_status_written", -math.inf) > 10 or final:
                self.write_status("running")
        if self.val_loader is not None and (it % self.cfg.val.every == 0 or final):
            self._validate_and_save(it)
        if it % self.cfg.checkpoint.every == 0 or final:
            self.save_checkpoint()
            if self.val_loader is None:
                self._save_weights("model.safetensors")

    def request_stop(self, *_args) -> None:
        """Ask :meth:`fit` to checkpoint and return after the current step (a SIGTERM handler)."""
        self._stop_requested = True

    def _stop_reason(self, stop: int, after_step: bool = True) -> str | None:
        """Why to stop now (agreed by all ranks): None, ``done``, ``max_steps``, ``max_minutes`` or ``signal``.
        The time budget and a signal are looked at only ``after_step``, so every call of :meth:`fit` makes
        progress."""
        if not after_step:
            return "done" if self.iteration >= self.total else ("max_steps" if self.iteration >= stop else None)
        budget = self.cfg.train.max_minutes
        flags = torch.tensor(
            [
                float(budget is not None and time.monotonic() - self._clock0 >= 60.0 * budget),
                float(self._stop_requested),
            ]
        )
        if self.world > 1 and (budget is not None or self._handles_signal):
            backend_device = self.device if dist.get_backend() == "nccl" else torch.device("cpu")
            flags = flags.to(backend_device)
            dist.all_reduce(flags, op=dist.ReduceOp.MAX)
            flags = flags.cpu()
        if self.iteration >= self.total:
            return "done"
        if flags[1] > 0:
            return "signal"
        if flags[0] > 0:
            return "max_minutes"
        if self.iteration >= stop:
            return "max_steps"
        return None

    def fit(self, max_steps: int | None = None, handle_sigterm: bool = False) -> dict:
        """Train until the configured total, or until ``max_steps`` more iterations, ``train.max_minutes`` or a
        SIGTERM (``handle_sigterm``, main thread only): then checkpoint, write the weights and return.

        Returns:
            dict(iteration, total, loss, best_psnr, stopped: done | max_steps | max_minutes | signal).
        """
        if self.is_main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            import yaml

            write_text(self.run_dir / "config.yaml", yaml.safe_dump(self.cfg.to_dict(), sort_keys=False))
        stop = self.total if max_steps is None else min(self.total, self.iteration + max_steps)
        self._handles_signal = handle_sigterm
        previous = signal.signal(signal.SIGTERM, self.request_stop) if handle_sigterm else None
        self._fit_clock, self._fit_start_iter = time.monotonic(), self.iteration
        self.write_status("running")
        bar = None
        if self.is_main and self.progress:
            from tqdm import tqdm

            bar = tqdm(total=self.total, initial=self.iteration, desc="train", dynamic_ncols=True, file=sys.stderr)
        self._last_loss, start = math.nan, time.time()
        reason = self._stop_reason(stop, after_step=False)
        try:
            with self._own_rng():
                while reason is None:
                    epoch, done = divmod(self.iteration, self.iters_per_epoch)
                    self.sampler.set_epoch(epoch, skip=done * self.per_rank_batch)
                    for batch in self.loader:
                        lr = self.optimizer.param_groups[0]["lr"]  # the rate this step uses
                        loss, terms = self.train_step(self._to_device(batch))
                        self.iteration += 1
                        self._last_loss = loss
                        if bar is not None:
                            bar.update(1)
                            bar.set_postfix(loss=f"{loss:.4f}")
                        self._after_step(
                            {
                                "iter": self.iteration,
                                "epoch": epoch,
                                "lr": lr,
                                "loss": loss,
                                **terms,
                                "elapsed_s": round(time.time() - start, 3),
                            }
                        )
                        reason = self._stop_reason(stop)
                        if reason is not None:
                            break
                if reason != "done" and getattr(self, "_checkpoint_iteration", None) != self.iteration:
                    self.save_checkpoint()  # stopped early: leave a resumable state and the weights so far
                    self._save_weights("model.safetensors")
        finally:
            if bar is not None:
                bar.close()
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        if reason != "done" and self.is_main:
            log.info(
                "stopped at iteration %d/%d (%s); resumable from %s", self.iteration, self.total, reason, self.run_dir
            )
        self.write_status("finished" if reason == "done" else "stopped", reason=reason)
        return {
            "iteration": self.iteration,
            "total": self.total,
            "loss": self._last_loss,
            "best_psnr": self.best_psnr,
            "stopped": reason,
        }

    def close(self) -> None:
        if self.world > 1 and dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()


def _jsonable(obj):
    return json.loads(json.dumps(obj))
