"""Training loop (Sec. 3.3 / Sec. 4.1): Adam, cosine annealing lr → lr_min over the run, total batch split across
DDP processes, validation (PSNR/SSIM), JSON-lines log, atomic resumable checkpoints.

Run folder: ``last.pt`` (resume state: model, optimiser, scheduler, iteration, per-rank RNG states, config; loaded
with ``torch.load(weights_only=True)``), ``model.safetensors`` / ``best.safetensors`` (``save_pretrained``),
``log.jsonl``, ``config.yaml``. Only rank 0 writes. Resuming is exact with ``num_workers: 0``: the data order is a
function of (seed, epoch), the batches already consumed in the current epoch are skipped, and all RNG states return.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from contextlib import nullcontext
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, DistributedSampler, Sampler, Subset

from d2turb.device import resolve_device
from d2turb.errors import D2TurbError
from d2turb.io import atomic_path, write_text
from d2turb.train.config import model_kwargs
from d2turb.train.losses import build_loss

CHECKPOINT = "last.pt"
FORMAT = 1
_EMPTY = torch.zeros(0, dtype=torch.uint8)


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
    except ValueError:
        raise D2TurbError(f"environment variable {name} must be an integer, got {os.environ[name]!r}") from None


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


class Trainer:
    """``Trainer(cfg, run_dir).fit()``; ``cfg`` from :func:`d2turb.train.config.load_config`."""

    def __init__(self, cfg: dict, run_dir: str | os.PathLike, resume: bool = False, progress: bool | None = None):
        from d2turb.models import create_model

        self.cfg, self.run_dir = cfg, Path(run_dir)
        if resume and not (self.run_dir / CHECKPOINT).is_file():
            raise D2TurbError(f"--resume: no checkpoint {self.run_dir / CHECKPOINT}")
        tcfg = cfg["train"]
        self.rank, self.world, self.device = init_distributed(tcfg["device"])
        self.is_main = self.rank == 0
        if tcfg["batch"] % self.world:
            raise D2TurbError(f"train.batch {tcfg['batch']} is not divisible by the {self.world} processes")
        self.per_rank_batch = tcfg["batch"] // self.world
        if tcfg["amp"] == "bf16" and self.device.type not in ("cuda", "cpu"):
            raise D2TurbError(f"train.amp bf16 is not supported on {self.device.type}")
        self.progress = cfg["log"]["progress"] if progress is None else progress

        torch.manual_seed(tcfg["seed"])  # identical initial weights on every rank
        name, kwargs = model_kwargs(cfg)
        self.model = create_model(name, **kwargs).to(self.device).train()
        self.loss = build_loss(cfg["loss"], self.model, self.device, warn=self.is_main)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=tcfg["lr"], betas=tuple(tcfg["betas"]), weight_decay=tcfg["weight_decay"]
        )
        self.dataset, self.synthesis = self._build_data()
        self.sampler = ResumableSampler(self.dataset, self.world, self.rank, tcfg["seed"])
        self.iters_per_epoch = len(self.sampler) // self.per_rank_batch
        if self.iters_per_epoch < 1:
            raise D2TurbError(
                f"the training set has {len(self.dataset)} samples, fewer than one batch of "
                f"{self.per_rank_batch} per process"
            )
        self.total = tcfg["iterations"] or tcfg["epochs"] * self.iters_per_epoch
        self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            self.optimizer, T_max=self.total, eta_min=tcfg["lr_min"]
        )
        self.loader_generator = torch.Generator().manual_seed(tcfg["seed"] + self.rank)
        self.loader = DataLoader(
            self.dataset,
            batch_size=self.per_rank_batch,
            sampler=self.sampler,
            drop_last=True,
            num_workers=cfg["data"]["num_workers"],
            generator=self.loader_generator,
            pin_memory=self.device.type == "cuda",
        )
        self.val_loader = self._build_val()
        torch.manual_seed(tcfg["seed"] + 7919 * self.rank)  # per-rank augmentation stream
        self.ddp = self.model
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel

            self.ddp = DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None
            )
        self.iteration, self.best_psnr = 0, -math.inf
        ckpt = self.run_dir / CHECKPOINT
        if ckpt.is_file():
            self.load_checkpoint(ckpt)

    # ---------------------------------------------------------------- data
    def _build_data(self):
        data = self.cfg["data"]
        if data["pairs"] is not None:
            from d2turb.data import PairDataset

            crop = data["patch"]
            probe = PairDataset(data["pairs"])
            return PairDataset(
                data["pairs"], crop=min(crop, probe.patch), hflip=data["hflip"], vflip=data["vflip"]
            ), None
        from d2turb.data import CleanCropDataset, OnTheFlySynthesis
        from d2turb.data.generate import simulator_params
        from d2turb.sim import Simulator

        otf = data["on_the_fly"]
        dataset = CleanCropDataset(
            data["clean"], patch=data["patch"], depth_spec=otf["depth"], length=otf["length"], hflip=data["hflip"]
        )
        params, _ = simulator_params(otf["params"] or {})
        synthesis = OnTheFlySynthesis(
            Simulator(params, self.device),
            bins=tuple(otf["bins"]),
            device=self.device,
            seed=self.cfg["train"]["seed"] + self.rank,
            use_depth=otf["depth"] != "none",
        )
        return dataset, synthesis

    def _build_val(self):
        val = self.cfg["val"]
        if val["pairs"] is None:
            return None
        from d2turb.data import PairDataset

        dataset = PairDataset(val["pairs"])
        n = len(dataset) if val["max_images"] is None else min(len(dataset), int(val["max_images"]))
        shard = Subset(dataset, list(range(self.rank, n, self.world)))
        return DataLoader(shard, batch_size=val["batch"], shuffle=False, num_workers=0)

    def _to_device(self, batch: dict) -> dict:
        if self.synthesis is not None:
            return self.synthesis(batch)
        return {k: v.to(self.device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}

    # ---------------------------------------------------------------- state
    def _rng_state(self) -> dict:
        cuda = torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else _EMPTY
        synth = self.synthesis.generator.get_state() if self.synthesis is not None else _EMPTY
        return {
            "cpu": torch.get_rng_state(),
            "cuda": cuda.cpu(),
            "synth": synth.cpu(),
            "loader": self.loader_generator.get_state(),
        }

    def _set_rng_state(self, state: dict) -> None:
        torch.set_rng_state(state["cpu"])
        if self.device.type == "cuda" and state["cuda"].numel():
            torch.cuda.set_rng_state(state["cuda"], self.device)
        if self.synthesis is not None and state["synth"].numel():
            self.synthesis.generator.set_state(state["synth"])
        self.loader_generator.set_state(state["loader"])

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
            "config": json.dumps(self.cfg),
        }
        path = self.run_dir / CHECKPOINT
        with atomic_path(path) as tmp:
            torch.save(state, tmp)
        return path

    def load_checkpoint(self, path: Path) -> None:
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            saved_cfg = json.loads(state["config"])
        except Exception as exc:  # truncated file, foreign pickle, missing keys
            raise D2TurbError(f"{path}: unreadable checkpoint ({exc.__class__.__name__})") from None
        if saved_cfg.get("model") != self.cfg["model"]:
            raise D2TurbError(
                f"{path}: checkpoint is for model {saved_cfg.get('model')}, not {self.cfg['model']}; "
                "use another --out folder"
            )
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.iteration, self.best_psnr = int(state["iteration"]), float(state["best_psnr"])
        if state["world_size"] == self.world:
            self._set_rng_state(state["rng"][self.rank])
        elif self.is_main:
            print(
                f"warning: resuming a {state['world_size']}-process run on {self.world}; "
                "data order and RNG streams restart",
                file=sys.stderr,
            )

    def _log(self, record: dict) -> None:
        if self.is_main:
            with open(self.run_dir / "log.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")

    def _save_weights(self, name: str) -> None:
        if self.is_main:
            from d2turb.models import save_pretrained

            save_pretrained(self.model, self.run_dir / name)

    # ---------------------------------------------------------------- steps
    def train_step(self, batch: dict) -> tuple[float, dict]:
        amp = (
            torch.autocast(self.device.type, dtype=torch.bfloat16)
            if self.cfg["train"]["amp"] == "bf16"
            else nullcontext()
        )
        with amp:
            out = self.ddp(batch["turb"])
        loss, terms = self.loss(out, batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        clip = self.cfg["train"]["grad_clip"]
        if clip:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), float(clip))
        self.optimizer.step()
        self.scheduler.step()
        return float(loss.detach()), terms

    @torch.no_grad()
    def validate(self) -> dict:
        """Mean PSNR/SSIM of ``restored`` (clamped to [0, 1]) on the validation pairs, over all ranks."""
        from d2turb.data import crop_sample
        from d2turb.eval.metrics import PSNR, SSIM

        psnr, ssim = PSNR(), SSIM()
        crop = self.cfg["val"]["crop"]
        self.model.eval()
        for batch in self.val_loader:
            if crop:
                h, w = batch["gt"].shape[-2:]
                size = min(crop, h, w)
                batch = crop_sample(batch, (h - size) // 2, (w - size) // 2, size)  # deterministic centre crop
            out = self.model(batch["turb"].to(self.device))
            restored = out["restored"].float().clamp(0, 1).cpu()
            psnr.update(restored, batch["gt"])
            ssim.update(restored, batch["gt"])
        self.model.train()
        return {"psnr": psnr.compute(), "ssim": ssim.compute()}

    def _after_step(self, record: dict) -> None:
        it, final = self.iteration, self.iteration >= self.total
        if it % self.cfg["log"]["every"] == 0 or final:
            self._log(record)
        if self.val_loader is not None and (it % self.cfg["val"]["every"] == 0 or final):
            metrics = self.validate()
            self._log({"iter": it, "val_psnr": metrics["psnr"], "val_ssim": metrics["ssim"]})
            self._save_weights("model.safetensors")
            if metrics["psnr"] > self.best_psnr:
                self.best_psnr = metrics["psnr"]
                self._save_weights("best.safetensors")
        if it % self.cfg["checkpoint"]["every"] == 0 or final:
            self.save_checkpoint()
            if self.val_loader is None:
                self._save_weights("model.safetensors")

    def fit(self, max_steps: int | None = None) -> dict:
        """Train until the configured total (or ``max_steps`` more iterations, then checkpoint and stop)."""
        if self.is_main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            import yaml

            write_text(self.run_dir / "config.yaml", yaml.safe_dump(self.cfg, sort_keys=False))
        stop = self.total if max_steps is None else min(self.total, self.iteration + max_steps)
        bar = None
        if self.is_main and self.progress:
            from tqdm import tqdm

            bar = tqdm(total=self.total, initial=self.iteration, desc="train", dynamic_ncols=True, file=sys.stderr)
        last_loss, start = math.nan, time.time()
        while self.iteration < stop:
            epoch, done = divmod(self.iteration, self.iters_per_epoch)
            self.sampler.set_epoch(epoch, skip=done * self.per_rank_batch)
            for batch in self.loader:
                lr = self.optimizer.param_groups[0]["lr"]  # the rate this step uses
                loss, terms = self.train_step(self._to_device(batch))
                self.iteration += 1
                last_loss = loss
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
                if self.iteration >= stop:
                    break
        if bar is not None:
            bar.close()
        if self.iteration < self.total and self.iteration % self.cfg["checkpoint"]["every"]:
            self.save_checkpoint()  # stopped early (max_steps): leave a resumable state
        return {"iteration": self.iteration, "total": self.total, "loss": last_loss, "best_psnr": self.best_psnr}

    def close(self) -> None:
        if self.world > 1 and dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()
