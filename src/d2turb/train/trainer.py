"""Training loop (Sec. 3.3 / Sec. 4.1): Adam, cosine annealing lr → lr_min over the run, total batch split across
DDP processes, validation (PSNR/SSIM, flow end-point error), JSON-lines log, atomic resumable checkpoints, an EMA
of the weights, bf16 autocast / channels_last / torch.compile options and a time budget for short GPU jobs.

Run folder: ``last.pt`` (resume state, :mod:`d2turb.train.checkpoint`), ``model.safetensors`` /
``best.safetensors`` (``save_pretrained``; the EMA weights when ``train.ema`` is set), ``log.jsonl`` and
``status.json`` (:mod:`d2turb.train.status`), ``config.yaml``. Only rank 0 writes. Resuming is exact with
``num_workers: 0``: the data order is a function of (seed, epoch), the batches already consumed in the current epoch
are skipped, and all RNG states return. The trainer never seeds the process-wide RNG: it draws from its own
generators and, while it trains, swaps its own CPU/CUDA RNG state in (:class:`~d2turb.train.checkpoint.RngStreams`)
so that dataset augmentations that use the global RNG stay reproducible, and the caller's state comes back
afterwards. DDP plumbing: :mod:`d2turb.train.distributed`; validation: :mod:`d2turb.train.validation`.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import time
import warnings
from contextlib import nullcontext
from pathlib import Path

import torch
import torch.distributed as dist

from d2turb.device import distributed_env
from d2turb.errors import D2TurbError
from d2turb.io import remove_stale_temp_files
from d2turb.models import create_model, save_pretrained
from d2turb.train.checkpoint import CHECKPOINT, RngStreams, load_checkpoint, load_weights, save_checkpoint
from d2turb.train.config import Config, model_kwargs
from d2turb.train.data import TrainingData
from d2turb.train.distributed import all_reduce_values, gather_objects, init_distributed, shutdown, wrap_ddp
from d2turb.train.ema import EMA
from d2turb.train.losses import build_loss
from d2turb.train.status import STATUS, RunProgress, read_status
from d2turb.train.stopping import StopConditions
from d2turb.train.validation import Validation

__all__ = ["CHECKPOINT", "STATUS", "Trainer", "init_distributed", "read_status"]  # and the names imported from here

_AUG_SEED_STRIDE = 7919  # per-rank offset of the trainer's own RNG streams
log = logging.getLogger("d2turb.train")


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
        tcfg = self.cfg.train
        self.run_dir = Path(run_dir)
        self.progress = self.cfg.log.progress if progress is None else progress
        clock0_s = time.monotonic()  # the time budget counts from here (data decoding included)
        self.checkpoint_path = self.run_dir / CHECKPOINT
        self.resuming = self._check_resume(resume)
        self.rank, self.world, self.device = init_distributed(tcfg.device)
        self.is_main = self.rank == 0
        self.per_rank_batch = self._per_rank_batch()
        self.run_progress = RunProgress(self.run_dir, self.is_main, clock0_s)
        self.model = self._build_model()
        self.loss = build_loss(dict(vars(self.cfg.loss)), self.model, self.device, warn=self.is_main)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=tcfg.lr, betas=tuple(tcfg.betas), weight_decay=tcfg.weight_decay
        )
        aug_seed = tcfg.seed + _AUG_SEED_STRIDE * self.rank  # this rank's augmentation streams
        self.data = TrainingData(
            self.cfg, self.rank, self.world, self.device, self.per_rank_batch, aug_seed, warn=self.is_main
        )
        self.total = tcfg.iterations or tcfg.epochs * self.data.iters_per_epoch
        self.stopping = StopConditions(self.total, tcfg.max_minutes, clock0_s, self.world)
        self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            self.optimizer, T_max=self.total, eta_min=tcfg.lr_min
        )
        self.rng = RngStreams(aug_seed, self.device, self.data.synthesis, self.data.loader_generator, self.data.dataset)
        self.validation = Validation(self.cfg, self.rank, self.world, self.device, self.data.make_synthesis)
        self.val_loader = self.validation.batches  # None without validation
        self.ema = EMA(self.model, tcfg.ema) if tcfg.ema is not None else None
        self.ddp = wrap_ddp(self.model, self.device, self.world)
        backend = "inductor" if tcfg.compile is True else tcfg.compile
        self.forward = torch.compile(self.ddp, backend=backend) if tcfg.compile else self.ddp
        self.iteration, self.best_psnr = 0, -math.inf
        self._last_loss: float | None = None
        self._last_val: dict | None = None
        self._checkpoint_iteration: int | None = None
        self._restore_or_init()

    # ---------------------------------------------------------------- construction steps
    def _check_resume(self, resume: bool) -> bool:
        """Whether ``last.pt`` exists (required by ``resume``); rank 0 first removes a killed run's temp files."""
        if distributed_env().rank == 0:  # temp checkpoints (hundreds of MB) of a killed run, before anything is written
            remove_stale_temp_files(self.run_dir)
        if resume and not self.checkpoint_path.is_file():
            raise D2TurbError(f"resume: no checkpoint {self.checkpoint_path}", param="resume")
        return self.checkpoint_path.is_file()

    def _per_rank_batch(self) -> int:
        tcfg = self.cfg.train
        if tcfg.batch % self.world:
            raise D2TurbError(f"train.batch {tcfg.batch} is not divisible by the {self.world} processes")
        if tcfg.amp == "bf16" and self.device.type not in ("cuda", "cpu"):
            raise D2TurbError(f"train.amp bf16 is not supported on {self.device.type}")
        return tcfg.batch // self.world

    def _build_model(self) -> torch.nn.Module:
        """The model, created from ``train.seed`` (identical on every rank) without touching the global RNG."""
        name, kwargs = model_kwargs(self.cfg)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.cfg.train.seed)
            model = create_model(name, **kwargs)
        model = model.to(self.device).train()
        return model.to(memory_format=torch.channels_last) if self.cfg.train.channels_last else model

    def _restore_or_init(self) -> None:
        if self.resuming:
            self.load_checkpoint(self.checkpoint_path)
            if self.cfg.train.init_from and self.is_main:
                log.info("resuming %s at iteration %d; train.init_from ignored", self.run_dir, self.iteration)
        elif self.cfg.train.init_from:
            self.init_from(self.cfg.train.init_from)

    # ---------------------------------------------------------------- weights and state
    def init_from(self, weights: str | os.PathLike) -> None:
        """Load weights only (no optimiser or schedule) from a d2turb ``.safetensors`` file or weights name
        (:func:`d2turb.train.checkpoint.load_weights`: same model config, strict). The EMA restarts from them."""
        path = load_weights(self.model, weights)
        if self.ema is not None:
            self.ema = EMA(self.model, self.cfg.train.ema)
        if self.is_main:
            log.info("initialised from %s", path)

    def save_checkpoint(self) -> Path | None:
        """Atomically write ``last.pt`` (rank 0; every rank contributes its RNG state)."""
        rngs = gather_objects(self.rng.state_dict(), self.world)
        self._checkpoint_iteration = self.iteration  # on every rank: fit's final save is a collective
        if not self.is_main:
            return None
        save_checkpoint(
            self.checkpoint_path,
            iteration=self.iteration,
            world=self.world,
            best_psnr=self.best_psnr,
            model=self.model,
            optimizer=self.optimizer,
            scheduler=self.scheduler,
            ema=self.ema,
            rng=rngs,
            config=self.cfg.to_dict(),
        )
        return self.checkpoint_path

    def load_checkpoint(self, path: Path) -> None:
        """Resume from ``path``: weights, EMA, optimiser, schedule, iteration, best PSNR and, with the same number
        of processes, every RNG stream; ``log.jsonl`` loses the lines of the iterations after it."""
        state = load_checkpoint(path, self.cfg.model, self.model, self.optimizer, self.scheduler)
        self.iteration, self.best_psnr = int(state["iteration"]), float(state["best_psnr"])
        self._checkpoint_iteration = self.iteration
        self.run_progress.truncate_log(self.iteration)
        if self.ema is not None:
            if "ema" in state:
                self.ema.load_state_dict(state["ema"])
            else:
                self.ema = EMA(self.model, self.cfg.train.ema)
                if self.is_main:
                    warnings.warn(f"{path} has no EMA weights; the EMA starts from the current weights", stacklevel=2)
        if state["world_size"] == self.world:
            self.rng.load_state_dict(state["rng"][self.rank])
        elif self.is_main:
            warnings.warn(
                f"resuming a {state['world_size']}-process run on {self.world}; data order and RNG streams restart",
                stacklevel=2,
            )

    @property
    def eval_model(self) -> torch.nn.Module:
        """The weights that validate and ship: the EMA when ``train.ema`` is set, else the trained model."""
        return self.ema.model if self.ema is not None else self.model

    def _save_weights(self, name: str) -> None:
        if self.is_main:
            save_pretrained(self.eval_model, self.run_dir / name)

    def write_status(self, state: str, **extra) -> None:
        """Write ``status.json`` (rank 0): state, pid, progress, speed, ETA, last loss and validation."""
        self.run_progress.write_status(
            state,
            iteration=self.iteration,
            total=self.total,
            max_minutes=self.cfg.train.max_minutes,
            loss=self._last_loss,
            val=self._last_val,
            checkpoint_iteration=self._checkpoint_iteration,
            **extra,
        )

    # ---------------------------------------------------------------- steps
    def _autocast(self):
        if self.cfg.train.amp == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return nullcontext()

    def _input(self, image: torch.Tensor) -> torch.Tensor:
        image = image.to(self.device, non_blocking=True)
        return image.contiguous(memory_format=torch.channels_last) if self.cfg.train.channels_last else image

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
        if all_reduce_values(finite, dist.ReduceOp.MIN, self.world).item() == 0:
            tcfg = self.cfg.train
            raise D2TurbError(
                f"loss became non-finite at iteration {self.iteration + 1} ({float(loss.detach())} on rank "
                f"{self.rank}): training diverged; lower train.lr (now {tcfg.lr}) or set train.grad_clip "
                f"(now {tcfg.grad_clip}); the last checkpoint is kept"
            )

    def validate(self) -> dict:
        """Mean metrics of the evaluation weights (:attr:`eval_model`) on the validation set, over all ranks (see
        :meth:`d2turb.train.validation.Validation.metrics`): ``psnr``, ``ssim``, ``psnr_input``, ``ssim_input``,
        ``epe``, ``epe_zero`` and the same per bin as ``<metric>_<bin>``."""
        if self.val_loader is None:
            raise D2TurbError("no validation set: set val.pairs or val.pack")
        return self.validation.metrics(self.eval_model, self._input, self._autocast)

    def _validate_and_save(self, it: int) -> None:
        metrics = self.validate()
        self._last_val = {"iter": it, **metrics}
        self.run_progress.log({"iter": it, **{f"val_{k}": v for k, v in metrics.items()}, "ema": self.ema is not None})
        self._save_weights("model.safetensors")
        if metrics.get("psnr", -math.inf) > self.best_psnr:
            self.best_psnr = metrics["psnr"]
            self._save_weights("best.safetensors")

    def _after_step(self, record: dict) -> None:
        it, final = self.iteration, self.iteration >= self.total
        if it % self.cfg.log.every == 0 or final:
            self.run_progress.log(record)
            if self.run_progress.status_due() or final:
                self.write_status("running")
        if self.val_loader is not None and (it % self.cfg.val.every == 0 or final):
            self._validate_and_save(it)
        if it % self.cfg.checkpoint.every == 0 or final:
            self.save_checkpoint()
            if self.val_loader is None:
                self._save_weights("model.safetensors")

    def request_stop(self, *_args) -> None:
        """Ask :meth:`fit` to checkpoint and return after the current step (a SIGTERM handler)."""
        self.stopping.request()

    def _train(self, stop: int, bar, start: float) -> str:
        """Steps until :attr:`stopping` gives a reason; returns it."""
        reason = self.stopping.reason(self.iteration, stop, after_step=False)
        while reason is None:
            epoch, done = divmod(self.iteration, self.data.iters_per_epoch)
            self.data.sampler.set_epoch(epoch, skip=done * self.per_rank_batch)
            for batch in self.data.loader:
                lr = self.optimizer.param_groups[0]["lr"]  # the rate this step uses
                loss, terms = self.train_step(self.data.to_device(batch))
                self.iteration += 1
                self._last_loss = loss
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{loss:.4f}")
                elapsed = round(time.time() - start, 3)
                self._after_step(
                    {"iter": self.iteration, "epoch": epoch, "lr": lr, "loss": loss, **terms, "elapsed_s": elapsed}
                )
                reason = self.stopping.reason(self.iteration, stop)
                if reason is not None:
                    break
        return reason

    def fit(self, max_steps: int | None = None, handle_sigterm: bool = False) -> dict:
        """Train until the configured total, or until ``max_steps`` more iterations, ``train.max_minutes`` or a
        SIGTERM (``handle_sigterm``, main thread only): then checkpoint, write the weights and return.

        Returns:
            dict(iteration, total, loss, best_psnr, stopped: done | max_steps | max_minutes | signal).
        """
        stop = self.total if max_steps is None else min(self.total, self.iteration + max_steps)
        self.run_progress.start_fit(self.iteration, self.cfg.to_dict())
        with self.stopping.sigterm_handled(handle_sigterm):
            self.write_status("running")
            bar = self.run_progress.progress_bar(self.total, self.iteration, show=self.progress)
            self._last_loss, start = math.nan, time.time()
            try:
                with self.rng.swapped_in():
                    reason = self._train(stop, bar, start)
                    if reason != "done" and self._checkpoint_iteration != self.iteration:
                        self.save_checkpoint()  # stopped early: leave a resumable state and the weights so far
                        self._save_weights("model.safetensors")
            finally:
                if bar is not None:
                    bar.close()
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
        """Leave the process group (after every rank got here); the DDP wrapper, whose reducer holds the group,
        goes first. DDP sits in reference cycles (its hooks), so it is collected here, not at interpreter exit after
        the group is gone, where gloo's worker threads can abort the process ("terminate called without an active
        exception", pytorch/pytorch#190489)."""
        self.ddp = self.model
        gc.collect()
        shutdown(self.world)
