"""Paired-dataset generation at scale: deterministic per-sample plans, batched simulation,
atomic per-sample writes, restartable, and data-parallel over ``torchrun`` ranks.

Determinism: sample ``i`` draws its source image, crop and D/r0 from ``(seed, i)`` alone; the simulator's
noise for the batch ("chunk") ``c = i // batch`` is seeded from ``(seed, c)``. Chunks are dealt to ranks
round-robin (``c ≡ rank mod world``; with ``--batch 1`` that is ``i ≡ rank mod world``), so for a given
seed, batch size and device the output does not depend on the number of processes or on restarts.

The settings and their record are :mod:`~d2turb.data.config`, what each sample draws :mod:`~d2turb.data.plan`;
the source images are read by :mod:`~d2turb.data.sources`; which samples are done, and the clean-up of an
unfinished run, is :mod:`~d2turb.data.resume`.
"""

from __future__ import annotations

import contextlib
import datetime
import threading
import time
from pathlib import Path

import numpy as np
import torch

from d2turb.data.config import DatasetConfig, dataset_config_record, params_record, validate
from d2turb.data.field import prepare_scene, simulate_field_chunk, window_margin
from d2turb.data.layout import (
    CONFIG_NAME,
    FILES,
    append_line,
    file_path,
    sample_id,
    truncate_partial_line,
    write_depth_png,
)
from d2turb.data.plan import chunk_geometry, chunk_seed, crop_box, keyed_rng, plan_sample
from d2turb.data.resume import (
    check_same_config,
    collect_records,
    discard_if_empty,
    merge_meta,
    remove_temp_files,
    reset_unfinished,
    shard_dir,
)
from d2turb.data.sequence import simulate_sequence_chunk
from d2turb.data.sources import SourceCache, check_patch_fits, make_depth_fn
from d2turb.device import DistributedEnv, distributed_env, resolve_device
from d2turb.errors import D2TurbError
from d2turb.io import (
    BackgroundWriter,
    FolderLock,
    check_output_dir,
    expand_inputs,
    write_image,
    write_json,
    write_npy,
)
from d2turb.ops.splat import invert_flow
from d2turb.sim import Simulator
from d2turb.sim.geometry import geometry_bank


def camera_degrade(turb: torch.Tensor, camera: dict, seed: int, index: int, rows: int) -> tuple[torch.Tensor, dict]:
    """Camera noise and JPEG on a sample's turbulent frames ((3, N·rows, W), frames stacked vertically), each
    drawn per sample from (seed, index) only: Gaussian noise of σ uniform in ``camera["noise"]`` grey levels, 8-bit
    quantisation, then each frame JPEG-compressed at a quality uniform in ``camera["jpeg"]`` (OpenCV)."""
    import cv2

    rng = keyed_rng(seed, 3, index)
    drawn = {}
    img = turb.float().clamp(0, 1).numpy().transpose(1, 2, 0) * 255
    if "noise" in camera:
        drawn["noise_grey"] = float(rng.uniform(*camera["noise"]))
        img = img + rng.normal(0.0, drawn["noise_grey"], img.shape)
    u8 = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    if "jpeg" in camera:
        drawn["jpeg_quality"] = int(rng.integers(camera["jpeg"][0], camera["jpeg"][1] + 1))
        for y in range(0, u8.shape[0], rows):
            bgr = np.ascontiguousarray(u8[y : y + rows, :, ::-1])
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, drawn["jpeg_quality"]])
            if not ok:
                raise D2TurbError("JPEG encoding failed")
            u8[y : y + rows] = cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1]
    return torch.from_numpy(u8.transpose(2, 0, 1).astype(np.float32) / 255), drawn


# ------------------------------------------------------------------------------------------ distributed
def _barrier(info: DistributedEnv) -> None:
    if info.world > 1:
        torch.distributed.barrier()


# ----------------------------------------------------------------------------------------------- driver
def generate_dataset(cfg: DatasetConfig, progress: bool = True) -> dict:
    """Generate (or finish) the dataset in ``cfg.out``; returns counts and timing of this process."""
    validate(cfg)
    info = distributed_env()
    resolve_device(cfg.device, info.local_rank)  # a bad --device fails before anything is written
    root = check_output_dir(cfg.out)
    sources = expand_inputs(list(cfg.clean))
    check_patch_fits(sources, cfg.patch)
    bank = geometry_bank(cfg.geometry, cfg.params)
    params_full = params_record(bank[0]) if cfg.geometry == "fixed" else [params_record(p) for p in bank]
    record = dataset_config_record(cfg, sources, params_full)
    created_root = not root.exists()
    initialized_here = False
    if info.world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group("gloo", timeout=datetime.timedelta(hours=2))
        initialized_here = True
    try:
        lock = _lock_folder(root, info)  # before anything is read or written: another run may be filling it
    except BaseException:
        if initialized_here:
            torch.distributed.destroy_process_group()
        if created_root:
            with contextlib.suppress(OSError):
                root.rmdir()
        raise
    try:
        # every rank checks, so a mismatch fails all of them before any barrier
        write_config = check_same_config(root, record)
        if info.rank == 0:
            root.mkdir(parents=True, exist_ok=True)
            remove_temp_files(root)
            if write_config:
                if (root / CONFIG_NAME).is_file():  # other settings, but no finished sample: start afresh
                    reset_unfinished(root)
                write_json(root / CONFIG_NAME, record)
        _barrier(info)
        stats = _generate_rank(cfg, info, root, sources, bank, progress)
        _barrier(info)
        if info.rank == 0:
            stats["total"] = merge_meta(root)
        _barrier(info)
    except BaseException:
        if lock is not None:
            lock.release()
        if info.world == 1 and root.is_dir():
            discard_if_empty(root, created_root)
        raise
    finally:
        if lock is not None:
            lock.release()
        if initialized_here:
            torch.distributed.destroy_process_group()
    return stats


def _lock_folder(root: Path, info: DistributedEnv) -> FolderLock | None:
    """Rank 0 locks ``root`` (:class:`d2turb.io.FolderLock`: a second make-dataset into it is refused in one line
    naming the first, a killed run's lock is taken over); every rank learns whether it succeeded."""
    lock, error = None, None
    if info.rank == 0:
        try:
            lock = FolderLock(root, "make-dataset").acquire()
        except D2TurbError as exc:
            error = exc
    if info.world > 1:
        flag = torch.tensor([0.0 if error is None else 1.0])
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
        if flag.item() and error is None and info.rank != 0:
            error = D2TurbError(f"{root} is in use by another make-dataset run (see rank 0)")
    if error is not None:
        raise error
    return lock


def _write_sample(root: Path, sid: str, sample: dict, meta: dict, shard: Path, lock, png_level: int) -> None:
    """The files of one sample, then its meta line: a sample is done once its line is in the shard."""
    for kind in ("turb", "tilt", "gt"):
        write_image(file_path(root, kind, sid), sample[kind], png_level)
    write_npy(file_path(root, "bwd_flow_px", sid), sample["bwd_flow_px"].numpy().astype(np.float16))
    write_depth_png(file_path(root, "depth", sid), sample["depth"], png_level)
    with lock:
        append_line(shard, meta)


def _chunk_indices(cfg: DatasetConfig, chunk: int) -> range:
    """The sample indices of chunk ``chunk``."""
    return range(chunk * cfg.batch, min((chunk + 1) * cfg.batch, cfg.pairs))


def _my_chunks(cfg: DatasetConfig, info: DistributedEnv, done: set) -> tuple[list[int], int]:
    """This rank's chunks that still hold a sample to make, and how many such samples they hold."""
    n_chunks = (cfg.pairs + cfg.batch - 1) // cfg.batch
    my_chunks = [
        c
        for c in range(info.rank, n_chunks, info.world)
        if any(sample_id(i) not in done for i in _chunk_indices(cfg, c))
    ]
    todo = sum(1 for c in my_chunks for i in _chunk_indices(cfg, c) if sample_id(i) not in done)
    return my_chunks, todo


def _open_shard(root: Path, info: DistributedEnv) -> Path:
    """This rank's meta shard (a partial last line from a killed run cut off) and the sample folders."""
    shard = shard_dir(root) / f"rank-{info.rank}.jsonl"
    shard.parent.mkdir(parents=True, exist_ok=True)
    truncate_partial_line(shard)
    for kind in FILES:
        (root / kind).mkdir(parents=True, exist_ok=True)
    return shard


def _sample_meta(cfg: DatasetConfig, plan, source: str, box, image, chunk: int, params_full: dict, g: int) -> dict:
    """The meta line of one sample (before what its simulation draws: the camera, the field clip)."""
    x0, y0, x1, y1 = box
    return {
        "id": plan.id,
        "index": plan.index,
        "split": cfg.split,
        "source": source,
        "crop": [x0, y0, x1, y1],
        "source_size": [int(image.shape[-1]), int(image.shape[-2])],
        "dr0": plan.dr0,
        "bin": plan.bin,
        "seed": cfg.seed,
        "chunk": chunk,
        "sim_seed": chunk_seed(cfg.seed, chunk),
        "depth": cfg.depth,
        "params": params_full,
        "geometry": g,
    }


def _read_chunk(
    cfg, chunk, g, plans, sources, cache, object_cache, params_full, phase
) -> tuple[list, list, list, list]:
    """The chunk's clean crops, depth crops, meta lines and (field profile) scenes, one per plan."""
    clean, depth, metas, scenes = [], [], [], []
    for plan in plans:
        if plan.source not in cache.cache:
            phase("reading source images" + ("" if cfg.depth == "none" else f" + depth ({cfg.depth})"))
        k, image, dmap = cache.get(plan.source)
        if cfg.profile == "field":
            scene = prepare_scene(plan, cfg, image, dmap, object_cache, len(sources), k)
            scenes.append(scene)
            box = scene["window"]
            clean.append(None)
            depth.append(None if scene["depth"] is None else torch.from_numpy(scene["depth"][:1]))
        else:
            box = x0, y0, x1, y1 = crop_box(plan, image.shape[-2], image.shape[-1], cfg.patch)
            clean.append(image[:, y0:y1, x0:x1])
            depth.append(None if dmap is None else dmap[:, y0:y1, x0:x1])
        metas.append(_sample_meta(cfg, plan, str(sources[k]), box, image, chunk, params_full, g))
    return clean, depth, metas, scenes


def _chunk_samples(cfg, chunk, sim, plans, inputs, dr0, generator, device, done):
    """Simulate one chunk; yield (plan, sample, meta) for each of its samples not yet done."""
    clean, depth, metas, scenes = inputs
    if cfg.profile == "field":  # each clip's own frames, camera and ground truth per frame
        field_samples = simulate_field_chunk(sim, scenes, dr0, generator, cfg.frames, cfg.sequence, device)
        for plan, meta, scene, sample, d in zip(plans, metas, scenes, field_samples, depth):
            if plan.id in done:
                continue
            sample["depth"] = d if d is not None else torch.ones(1, cfg.patch, cfg.patch)
            yield plan, sample, meta | {"field": scene["draw"]}
        return
    clean_t = torch.stack(clean).to(device)
    depth_t = None if depth[0] is None else torch.stack(depth).to(device)
    if cfg.frames > 1:  # sequences: frames stacked vertically, bwd_flow_px (B, N, 2, H, W)
        turb, tilt, bwd_flow_px = simulate_sequence_chunk(
            sim, clean_t, depth_t, dr0, generator, cfg.frames, cfg.sequence
        )
    else:
        res = sim(clean_t, depth=depth_t, dr0=dr0, generator=generator)
        turb, tilt, bwd_flow_px = res.turb, res.tilt, invert_flow(res.fwd_flow_px).float()
    if not torch.isfinite(bwd_flow_px).all() or not torch.isfinite(turb).all():
        raise D2TurbError(f"simulator produced NaN/inf for chunk {chunk} (samples {plans[0].id}..{plans[-1].id})")
    turb, tilt, bwd_flow_px = turb.float().cpu(), tilt.float().cpu(), bwd_flow_px.cpu()
    for b, (plan, meta) in enumerate(zip(plans, metas)):
        if plan.id in done:
            continue
        frames_b = turb[b]
        if cfg.camera:
            frames_b, drawn = camera_degrade(frames_b, cfg.camera, cfg.seed, plan.index, cfg.patch)
            meta = meta | {"camera": drawn}
        sample = {
            "turb": frames_b,
            "tilt": tilt[b],
            "gt": clean[b],
            "bwd_flow_px": bwd_flow_px[b],
            "depth": depth[b] if depth[b] is not None else torch.ones(1, cfg.patch, cfg.patch),
        }
        yield plan, sample, meta


def _generate_rank(cfg, info, root, sources, bank, progress) -> dict:
    device = resolve_device(cfg.device, info.local_rank)
    done = set(collect_records(root))
    my_chunks, todo = _my_chunks(cfg, info, done)
    shard = _open_shard(root, info)
    sims: dict[int, Simulator] = {}
    window, object_cache = cfg.patch, None
    if cfg.profile == "field":  # the frame's window with the border the camera's shake brings into view
        window = cfg.patch + 2 * window_margin(cfg.patch)
        object_cache = SourceCache(sources, window, None)
    cache = SourceCache(sources, window, make_depth_fn(cfg.depth, device, cfg.depth_is_disparity))
    bar = None
    if progress and info.rank == 0:
        from tqdm import tqdm

        bar = tqdm(total=todo, unit="pair", desc=f"make-dataset (rank 0 of {info.world})", dynamic_ncols=True)

    def phase(text: str) -> None:  # what the bar is waiting for (the first pairs take a while: sources, depth, PSFs)
        if bar is not None:
            bar.set_postfix_str(text, refresh=True)

    start, written = time.perf_counter(), 0
    shard_lock = threading.Lock()
    with torch.inference_mode(), BackgroundWriter(max_pending=2 * cfg.batch, compute_device=device) as writer:
        for c in my_chunks:
            plans = [plan_sample(i, cfg.seed, cfg.split, cfg.bins, len(sources)) for i in _chunk_indices(cfg, c)]
            g = chunk_geometry(cfg.seed, c, len(bank))
            if g not in sims:
                phase("setting up the simulator")
                sims[g] = Simulator(bank[g], device=str(device))
            sim, params_full = sims[g], params_record(bank[g])
            inputs = _read_chunk(cfg, c, g, plans, sources, cache, object_cache, params_full, phase)
            dr0 = torch.tensor([p.dr0 for p in plans], dtype=torch.float32, device=device)
            generator = torch.Generator(device=device).manual_seed(chunk_seed(cfg.seed, c))
            phase(f"simulating {len(plans)} pairs (PSFs and tilt for the whole batch at once)")
            writer.before_compute()
            new = 0
            for plan, sample, meta in _chunk_samples(cfg, c, sim, plans, inputs, dr0, generator, device, done):
                writer.submit(_write_sample, root, plan.id, sample, meta, shard, shard_lock, cfg.png_level)
                new += 1
            written += new
            if bar is not None:  # the chunk's pairs at once: one per-pair step would time 1 pair, not the chunk
                bar.update(new)
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - start
    return {
        "rank": info.rank,
        "world": info.world,
        "generated": written,
        "already_done": len(done),
        "seconds": seconds,
        "pairs_per_s": written / seconds if seconds > 0 else 0.0,
        "device": str(device),
    }
