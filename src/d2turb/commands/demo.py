"""`d2turb demo`: what the project does, in one figure and one table. Built-in samples under weak/medium/strong
depth-aware turbulence (simulation), a short simulated clip restored by the clip pipeline (registration, fusion,
physics deblur: it removes the tilt), and the shipped single-frame model on the same frames (it sharpens a little
and leaves the tilt), with per-bin PSNR/SSIM of the input, the clip restoration and the model."""

from __future__ import annotations

from d2turb.commands.common import add_seed_arg
from d2turb.commands.simulate import add_physics_args, physics_params
from d2turb.errors import D2TurbError

LEVELS = (("weak", 1.5), ("medium", 3.0), ("strong", 4.5))
DEMO_PATH_LENGTH_M = 3000.0  # the default aperture at Nyquist: tilt footprint 12.7 px, inside the training geometries
CLIP_IMAGE = "astronaut"  # the sample the clip is simulated from
CLIP_FRAMES = 16  # frames per bin; the clip pipeline's window spans them all
CLIP_WIND_M_S, CLIP_BOIL = 2.0, 0.1  # as the test clips of docs/clips.md
CLIP_STRIDE = 4  # every 4th frame is scored (as evaluate --clips)
ZOOM_BOX = (128, 64)  # (w, h) of the zoomed crop, shown 2x


def register(sub):
    p = sub.add_parser(
        "demo",
        help="simulate turbulence on built-in samples, restore a simulated clip and write a labelled figure",
        description="Writes DIR/demo.png, one labelled figure: (1) simulation: built-in images, clean | weak | "
        "medium | strong | depth | M; (2) a 16-frame clip simulated from one image per bin, restored by the clip "
        "pipeline (restore --temporal) beside the shipped single-frame model and the clean image, with zoomed crops. "
        "Also DIR/demo_clip.gif (input | clip restored, every frame), DIR/demo_results.md (per-bin PSNR/SSIM of "
        "the input, the clip restoration and the model) and per-image PNGs.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_seed_arg(p)
    p.add_argument(
        "--weights",
        metavar="NAME|FILE",
        help="single-frame restoration model (default: the recommended shipped model, see d2turb models); 'none' "
        "leaves it out",
    )
    add_physics_args(p, path_length_m=DEMO_PATH_LENGTH_M)
    p.set_defaults(func=run)


def _fmt_gain(value: float) -> str:
    return f"{value:+.2f}"


def run(args):
    # lazy: see d2turb.commands
    import torch

    from d2turb.data.samples import sample_images
    from d2turb.depth import estimate_depth_prior
    from d2turb.device import resolve_device
    from d2turb.io import check_output_dir, write_image, write_json, write_text
    from d2turb.sim import Simulator, depth_modulation

    out = check_output_dir(args.out)
    images = sample_images()
    names = list(images)
    params = physics_params(args)
    device = resolve_device(args.device)
    sim = Simulator(params, device=device)
    batch = torch.stack([images[n] for n in names])
    depth = estimate_depth_prior(batch)  # (B, 1, H, W), far = 1
    b = len(names)
    dr0 = torch.tensor([v for _, v in LEVELS], dtype=torch.float64).repeat_interleave(b)
    res = sim(
        batch.repeat(len(LEVELS), 1, 1, 1),
        depth=depth.repeat(len(LEVELS), 1, 1, 1),
        dr0=dr0,
        generator=torch.Generator().manual_seed(args.seed),
    )
    modulation = depth_modulation(depth, params.modulation, params.offset_s)
    meta = {"params": params.to_dict(), "seed": args.seed, "levels": dict(LEVELS), "images": names}
    for i, name in enumerate(names):
        write_image(out / f"{name}_depth.png", depth[i])
        for k, (level, _) in enumerate(LEVELS):
            write_image(out / f"{name}_{level}_turb.png", res.turb[k * b + i])
            write_image(out / f"{name}_{level}_tilt.png", res.tilt[k * b + i])
    print(f"simulated {b} images x {len(LEVELS)} bins (D/r0 {', '.join(f'{v:g}' for _, v in LEVELS)})")

    restorer = _restorer(args.weights, device)
    lines = ["# d2turb demo\n"]
    if restorer is not None:
        meta["restoration"], table = restore_single(restorer, res, names, out)
        lines += table
    k_clip = names.index(CLIP_IMAGE)
    clip = restore_clip(sim, params, images[CLIP_IMAGE], depth[k_clip], modulation[k_clip], args.seed, restorer, out)
    meta["clip"] = clip["record"]
    lines += clip["table"]
    text = "\n".join(lines) + "\n"
    write_text(out / "demo_results.md", text)
    print(text, end="")
    figure = demo_figure(images, res, depth, modulation, clip, restorer)
    write_image(out / "demo.png", figure)
    write_json(out / "demo_meta.json", meta)
    print(
        f"wrote {out / 'demo.png'} ({figure.shape[1]}x{figure.shape[0]}: simulation, clip restoration"
        f"{', single-frame model' if restorer is not None else ''}), {out / 'demo_clip.gif'} (input | clip restored)"
    )
    return 0


def _restorer(weights, device):
    """The single-frame model (None: ``--weights none``, or no shipped model: a note says so)."""
    if weights == "none":
        return None
    # lazy: the restorer (models) loads only when restoration is asked for
    from d2turb.models.hub import recommended_weights, resolve_weights
    from d2turb.restore import Restorer

    try:
        resolved = resolve_weights(weights) if weights is not None else recommended_weights()
    except D2TurbError as exc:
        if weights is not None:
            raise
        print(f"note: single-frame restoration skipped: {exc}")
        return None
    return Restorer(resolved, device=device)


def restore_single(restorer, res, names: list[str], out) -> tuple[dict, list[str]]:
    """The single-frame model on every simulated image; writes NAME_LEVEL_restored.png; returns (record, table
    lines). A model with a rectifier also gets the flow end-point errors."""
    # lazy: see d2turb.commands
    from d2turb.data.samples import SAMPLE_SIZE
    from d2turb.eval.metrics import KeyedMean, end_point_error, psnr, quantise_8bit, ssim
    from d2turb.io import write_image
    from d2turb.ops.splat import invert_flow

    details = restorer.restore_with_details(res.turb.float().cpu())
    has_flow = bool(details["bwd_flow_px"].any())  # a plain restorer (no rectifier) predicts no flow
    true_flow = invert_flow(res.fwd_flow_px).float().cpu()
    gt = res.clean.float().cpu()
    b = len(names)
    table = {}
    mean = KeyedMean(sync_on_compute=False)  # per bin, over the images
    for k, (level, value) in enumerate(LEVELS):
        for i, name in enumerate(names):
            j = k * b + i
            restored = quantise_8bit(details["restored"][j])  # what the saved PNG holds
            write_image(out / f"{name}_{level}_restored.png", restored)
            scores = {}
            for label, image in (("input", res.turb[j].float().cpu()), ("restored", restored)):
                scores[f"psnr_{label}"], scores[f"ssim_{label}"] = float(psnr(image, gt[j])), float(ssim(image, gt[j]))
            scores["epe_zero_flow_px"] = float(end_point_error(true_flow[j]))
            scores["epe_px"] = float(end_point_error(details["bwd_flow_px"][j], true_flow[j]))
            mean.update(scores, groups=level)
        means = mean.compute(level)
        keys = ["psnr_input", "psnr_restored", "ssim_input", "ssim_restored"]
        keys += ["epe_zero_flow_px", "epe_px"] if has_flow else []
        table[level] = {"dr0": value} | {key: means[key] for key in keys}
    header = "| bin | D/r0 | PSNR input | PSNR restored | gain (dB) | SSIM input | SSIM restored |"
    rule = "|---|---:|---:|---:|---:|---:|---:|"
    if has_flow:
        header, rule = header + " EPE zero flow (px) | EPE (px) |", rule + "---:|---:|"
    lines = [
        f"## Single frames: the single-frame model {restorer.name}\n",
        f"{len(names)} built-in images per bin, one simulated frame each, {SAMPLE_SIZE[1]}x{SAMPLE_SIZE[0]} px "
        "(a demo, not a benchmark: MODEL_CARD.md). It sharpens a little and leaves the tilt: its gain is small, "
        "and can be negative in a bin.\n",
        header,
        rule,
    ]
    for level, row in table.items():
        line = (
            f"| {level} | {row['dr0']:g} | {row['psnr_input']:.2f} | {row['psnr_restored']:.2f} | "
            f"{_fmt_gain(row['psnr_restored'] - row['psnr_input'])} | {row['ssim_input']:.3f} | "
            f"{row['ssim_restored']:.3f} |"
        )
        if has_flow:
            line += f" {row['epe_zero_flow_px']:.3f} | {row['epe_px']:.3f} |"
        lines.append(line)
    return {"weights": restorer.name, "table": table}, lines + [""]


def restore_clip(sim, params, image, depth, modulation, seed: int, restorer, out) -> dict:
    """A CLIP_FRAMES-frame clip of ``image`` per bin (frozen-flow turbulence moved by the wind, 8-bit frames),
    restored by the clip pipeline (window = the whole clip, physics deblur at the simulated D/r0 with the mean depth
    modulation, as ``evaluate --clips``), and every CLIP_STRIDE-th frame also by the single-frame model. Writes
    demo_clip.gif and clip_LEVEL_TT_{input,clip,model}.png (the frames scored and shown); returns the frames shown,
    the per-bin scores and the table lines."""
    # lazy: see d2turb.commands
    import numpy as np
    import torch
    from PIL import Image

    from d2turb.clip import ClipRestorer, PhysicsDeblur
    from d2turb.eval.metrics import KeyedMean, psnr, quantise_8bit, ssim
    from d2turb.io import atomic_path, write_image
    from d2turb.restore.compare import side_by_side

    n = len(LEVELS)
    dr0 = torch.tensor([v for _, v in LEVELS], dtype=torch.float64)
    frames = [[] for _ in range(n)]
    stream = sim.sequence(
        image[None].repeat(n, 1, 1, 1),
        frames=CLIP_FRAMES,
        wind=CLIP_WIND_M_S,
        boil=CLIP_BOIL,
        depth=depth[None].repeat(n, 1, 1, 1),
        dr0=dr0,
        generator=torch.Generator().manual_seed(seed + 1),
    )
    for res in stream:
        for k in range(n):
            frames[k].append(quantise_8bit(res.turb[k].float().cpu()))  # what a camera's 8-bit frame holds
    gt = image.float()
    scored = list(range(0, CLIP_FRAMES, CLIP_STRIDE))
    middle = CLIP_FRAMES // 2
    mean = KeyedMean(sync_on_compute=False)
    restored, shown, table = [], {}, {}
    for k, (level, value) in enumerate(LEVELS):
        deblur = PhysicsDeblur(value, params.lambda_over_d_px, modulation=float(modulation.mean()))
        clip = [quantise_8bit(f.restored) for f in ClipRestorer(temporal=CLIP_FRAMES, deblur=deblur).restore(frames[k])]
        restored.append(clip)
        model = None
        if restorer is not None:
            picks = torch.stack([frames[k][t] for t in sorted({*scored, middle})])
            model = dict(zip(sorted({*scored, middle}), quantise_8bit(restorer.restore(picks)).unbind(0)))
        for t in scored:
            scores = {"psnr_input": psnr(frames[k][t], gt), "psnr_clip": psnr(clip[t], gt)}
            scores |= {"ssim_input": ssim(frames[k][t], gt), "ssim_clip": ssim(clip[t], gt)}
            if model is not None:
                scores |= {"psnr_model": psnr(model[t], gt), "ssim_model": ssim(model[t], gt)}
            mean.update({key: float(v) for key, v in scores.items()}, groups=level)
        table[level] = {"dr0": value} | mean.compute(level)
        shown[level] = {
            "input": frames[k][middle],
            "clip": clip[middle],
            "model": None if model is None else model[middle],
        }
        for t in sorted({*scored, middle}):  # the frames scored and shown, as PNGs a user (or a test) can check
            write_image(out / f"clip_{level}_{t:02d}_input.png", frames[k][t])
            write_image(out / f"clip_{level}_{t:02d}_clip.png", clip[t])
            if model is not None:
                write_image(out / f"clip_{level}_{t:02d}_model.png", model[t])
    gif = []
    for t in range(CLIP_FRAMES):
        rows = [
            side_by_side([frames[k][t], restored[k][t]], (f"{lv}: input", f"{lv}: clip restored"))
            for k, (lv, _) in enumerate(LEVELS)
        ]
        gif.append(Image.fromarray(np.concatenate(rows, axis=0)).quantize(256, Image.Quantize.FASTOCTREE))
    with atomic_path(out / "demo_clip.gif") as tmp:
        gif[0].save(tmp, format="GIF", save_all=True, append_images=gif[1:], duration=100, loop=0)
    has_model = restorer is not None
    header = "| bin | D/r0 | PSNR input | PSNR clip | gain (dB) |" + (" PSNR model | gain (dB) |" if has_model else "")
    header += " SSIM input | SSIM clip |" + (" SSIM model |" if has_model else "")
    rule = "|---|---:|" + "---:|" * (header.count("|") - 3)
    lines = [
        f"## A clip: {CLIP_FRAMES} simulated frames of the {CLIP_IMAGE} per bin\n",
        f"Frozen-flow turbulence (wind {CLIP_WIND_M_S:g} m/s, boil {CLIP_BOIL:g}), 8-bit frames. Clip pipeline = "
        f"`d2turb restore --temporal {CLIP_FRAMES}` (registration, fusion, physics deblur at the simulated D/r0): "
        "it removes the tilt. "
        + (f"Model = the single-frame model {restorer.name} on the same frames. " if has_model else "")
        + f"Means over every {CLIP_STRIDE}th frame ({len(scored)} per bin).\n",
        header,
        rule,
    ]
    for level, row in table.items():
        line = f"| {level} | {row['dr0']:g} | {row['psnr_input']:.2f} | {row['psnr_clip']:.2f} | "
        line += f"{_fmt_gain(row['psnr_clip'] - row['psnr_input'])} |"
        if has_model:
            line += f" {row['psnr_model']:.2f} | {_fmt_gain(row['psnr_model'] - row['psnr_input'])} |"
        line += f" {row['ssim_input']:.3f} | {row['ssim_clip']:.3f} |"
        if has_model:
            line += f" {row['ssim_model']:.3f} |"
        lines.append(line)
    return {
        "table": lines,
        "shown": shown,
        "scores": table,
        "record": {
            "image": CLIP_IMAGE,
            "frames": CLIP_FRAMES,
            "window": CLIP_FRAMES,
            "wind_m_s": CLIP_WIND_M_S,
            "boil": CLIP_BOIL,
            "scored_frames": scored,
            "table": table,
        },
    }


def demo_figure(images, res, depth, modulation, clip: dict, restorer):
    """The demo's one figure: section 1 simulation (rows: images; columns: clean, the three bins, depth, M),
    section 2 the clip (rows: bins, each with a row of 2x crops; columns: input frame, clip restored, the
    single-frame model, clean)."""
    # lazy: see d2turb.commands
    from d2turb.eval.figure import Section, best_box, outline, render_section, stack, zoom
    from d2turb.io import to_uint8

    names = list(images)
    b = len(names)
    sim = Section(
        "1. Simulation: depth-aware turbulence on built-in images, one frame per bin (far = top: hit hardest)",
        ["clean"] + [f"{level}  D/r0 = {value:g}" for level, value in LEVELS] + ["depth (far = white)", "modulation M"],
    )
    for i, name in enumerate(names):
        cells = [to_uint8(images[name])] + [to_uint8(res.turb[k * b + i]) for k in range(len(LEVELS))]
        cells += [to_uint8(depth[i, 0].expand(3, -1, -1)), to_uint8(modulation[i, 0].expand(3, -1, -1))]
        sim.rows.append(([name], cells))
    model_name = restorer.name if restorer is not None else None
    columns = [f"input frame {CLIP_FRAMES // 2} of {CLIP_FRAMES}", f"clip pipeline ({CLIP_FRAMES} frames)"]
    columns += (["single-frame model"] if model_name else []) + ["clean"]
    title = (
        f"2. A simulated {CLIP_FRAMES}-frame clip of the {CLIP_IMAGE}, restored: the clip pipeline removes the tilt\n"
    )
    title += (
        f"The single-frame model ({model_name}) sharpens a little and leaves the tilt. PSNR: every "
        f"{CLIP_STRIDE}th frame"
        if model_name
        else f"PSNR: mean of every {CLIP_STRIDE}th frame"
    )
    section = Section(title, columns)
    clean = to_uint8(images[CLIP_IMAGE])
    strong = clip["shown"][LEVELS[-1][0]]
    gain = [(to_uint8(strong[k]).astype(float) - clean) ** 2 for k in ("input", "clip")]
    box = best_box((gain[0] - gain[1]).sum(axis=2), ZOOM_BOX)  # where the clip pipeline gains most (strong bin)
    for level, value in LEVELS:
        frames, row = clip["shown"][level], clip["scores"][level]
        cells = [to_uint8(frames["input"]), to_uint8(frames["clip"])]
        if frames["model"] is not None:
            cells.append(to_uint8(frames["model"]))
        cells.append(outline(clean, box))
        label = [level, f"D/r0 = {value:g}", f"input  {row['psnr_input']:.2f} dB"]
        label.append(f"clip   {row['psnr_clip']:.2f} ({_fmt_gain(row['psnr_clip'] - row['psnr_input'])})")
        if frames["model"] is not None:
            label.append(f"model  {row['psnr_model']:.2f} ({_fmt_gain(row['psnr_model'] - row['psnr_input'])})")
        section.rows.append((label, cells))
        crops = [zoom(c, box) for c in cells[:-1]] + [zoom(clean, box)]
        section.rows.append(([f"{level}: zoom 2x", "(yellow box)"], crops))
    return stack([render_section(sim), render_section(section)])
