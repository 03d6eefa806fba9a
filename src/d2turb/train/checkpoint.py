"""State of a training run: ``last.pt`` (model, EMA, optimiser, scheduler, iteration, per-rank RNG states, config;
read with ``torch.load(weights_only=True)``), the trainer's random streams that make a resumed run bit-identical to
an uninterrupted one, and weights-only initialisation (``train.init_from``)."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import torch

from d2turb.errors import D2TurbError
from d2turb.io import atomic_path
from d2turb.models import load_pretrained
from d2turb.models.hub import IDENTITY_NAME, resolve_weights

CHECKPOINT = "last.pt"
FORMAT = 1
NO_STATE = torch.zeros(0, dtype=torch.uint8)  # a stream this process does not have


class RngStreams:
    """The random streams of one training process, saved and restored as one state.

    The trainer's own CPU (and CUDA) global-RNG state, seeded from ``seed`` and swapped in only while it trains
    (:meth:`swapped_in`), so dataset augmentations that use the global RNG are reproducible and the caller's state
    is untouched; and the generators of the on-the-fly synthesis, the data loader and the dataset (pack crops).

    Args:
        seed: seed of the process's own global-RNG stream (differs per rank).
        device: the training device (a CUDA device adds a CUDA stream).
        synthesis: the on-the-fly synthesis (its ``generator``), or None.
        loader_generator: the DataLoader's generator.
        dataset: the training dataset; its ``generator`` attribute, if a ``torch.Generator``, is included.
    """

    def __init__(self, seed: int, device: torch.device, synthesis, loader_generator: torch.Generator, dataset):
        self.device, self.synthesis, self.loader_generator = device, synthesis, loader_generator
        data = getattr(dataset, "generator", None)
        self.data_generator = data if isinstance(data, torch.Generator) else None
        self.cuda = device.type == "cuda"
        self._cpu = torch.Generator().manual_seed(seed).get_state()
        self._cuda = torch.Generator(device=device).manual_seed(seed).get_state() if self.cuda else NO_STATE
        self._live = False

    @contextlib.contextmanager
    def swapped_in(self) -> Iterator[None]:
        """Swap the process's own CPU (and CUDA) RNG state in for the block; the caller's comes back afterwards."""
        with torch.random.fork_rng(devices=[self.device] if self.cuda else [], device_type="cuda"):
            torch.set_rng_state(self._cpu)
            if self.cuda:
                torch.cuda.set_rng_state(self._cuda, self.device)
            self._live = True
            try:
                yield
            finally:
                self._live = False
                self._cpu = torch.get_rng_state()
                if self.cuda:
                    self._cuda = torch.cuda.get_rng_state(self.device)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Every stream's state (CPU tensors; an absent stream is an empty tensor)."""
        live = self._live
        cuda = torch.cuda.get_rng_state(self.device) if live and self.cuda else self._cuda
        return {
            "cpu": torch.get_rng_state() if live else self._cpu,
            "cuda": cuda.cpu(),
            "synth": self.synthesis.generator.get_state().cpu() if self.synthesis is not None else NO_STATE,
            "loader": self.loader_generator.get_state(),
            "data": self.data_generator.get_state() if self.data_generator is not None else NO_STATE,
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore the streams of :meth:`state_dict` (empty entries leave a stream as it is)."""
        self._cpu = state["cpu"]
        if self.cuda and state["cuda"].numel():
            self._cuda = state["cuda"]
        if self.synthesis is not None and state["synth"].numel():
            self.synthesis.generator.set_state(state["synth"])
        self.loader_generator.set_state(state["loader"])
        if self.data_generator is not None and state.get("data", NO_STATE).numel():
            self.data_generator.set_state(state["data"])


def save_checkpoint(
    path: Path,
    *,
    iteration: int,
    world: int,
    best_psnr: float,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler,
    ema,
    rng: list[dict],
    config: dict,
) -> None:
    """Write the resume state to ``path``: ``torch.save`` to a temporary name, then rename, so an interrupted write
    leaves the previous file intact.

    Args:
        rng: every rank's :meth:`RngStreams.state_dict`, in rank order.
        ema: the :class:`~d2turb.train.ema.EMA`, or None.
        config: the run's config (``Config.to_dict()``).
    """
    state = {
        "format": FORMAT,
        "iteration": iteration,
        "world_size": world,
        "best_psnr": best_psnr,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "rng": rng,
        "config": json.dumps(config),
    }
    if ema is not None:
        state["ema"] = ema.state_dict()
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, model_cfg: dict, model: torch.nn.Module, optimizer, scheduler) -> dict:
    """Load the model, optimiser and scheduler states saved at ``path`` into the given objects.

    Returns:
        The whole saved state (``iteration``, ``best_psnr``, ``world_size``, ``rng``, ``ema`` if saved, ...).

    Raises:
        D2TurbError: an unreadable file (truncated, not a checkpoint) or a checkpoint of a model other than
        ``model_cfg``.
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        saved_cfg = json.loads(state["config"])
    except Exception as exc:  # truncated file, foreign pickle, missing keys
        raise D2TurbError(f"{path}: unreadable checkpoint ({exc.__class__.__name__})") from exc
    if saved_cfg.get("model") != model_cfg:
        raise D2TurbError(
            f"{path}: checkpoint is for model {saved_cfg.get('model')}, not {model_cfg}; use another --out folder"
        )
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    return state


def load_weights(model: torch.nn.Module, weights: str | os.PathLike) -> Path:
    """Load weights only (no optimiser or schedule) into ``model``, strictly, from a d2turb ``.safetensors`` file or
    weights name (resolved like ``d2turb restore --weights``).

    The file's model config must equal ``model.config`` (every weight is loaded), or the file must hold a plain
    backbone (a standalone restorer such as the shipped NAFNet models) whose config equals ``model.backbone``'s: then
    only the backbone is loaded, strictly, and the rest keeps its initialisation. D²Turb's rectifier starts with a
    zero flow head, so such a model starts as the backbone it was given: restored = Î_tilt = the backbone's output.

    Returns:
        The weights file.
    """
    path = resolve_weights(weights)
    if path == IDENTITY_NAME:
        raise D2TurbError(f"init_from {weights}: not a weights file", param="init_from")
    source = load_pretrained(path)  # verifies the checksum, strict
    if _jsonable(source.config) == _jsonable(model.config):
        model.load_state_dict(source.state_dict(), strict=True)
        return path
    backbone = getattr(model, "backbone", None)
    backbone_cfg = getattr(backbone, "config", None)
    if backbone_cfg is not None and hasattr(model, "rectifier") and _jsonable(source.config) == _jsonable(backbone_cfg):
        backbone.load_state_dict(source.backbone.state_dict(), strict=True)
        return path
    want = (
        _jsonable(model.config) if backbone_cfg is None else f"{_jsonable(model.config)} or its backbone {backbone_cfg}"
    )
    raise D2TurbError(
        f"init_from {path}: the weights are for model {_jsonable(source.config)}, not {want}", param="init_from"
    )


def _jsonable(obj):
    return json.loads(json.dumps(obj))
