"""`d2turb demo`: built-in samples under weak/medium/strong depth-aware turbulence, restored with the shipped
model: a simulation grid, a restoration grid (input | restored | clean, plus predicted and true flow for a model
with a rectifier) and a per-bin PSNR/SSIM table."""

from __future__ import annotations

from d2turb.commands.common import add_seed_arg
from d2turb.commands.simulate import add_physics_args, physics_params
from d2turb.errors import D2TurbError

LEVELS = (("weak", 1.5), ("medium", 3.0), ("strong", 4.5))
DEMO_PATH_LENGTH_M = 3000.0  # D = 0.1 m at Nyquist: tilt footprint 12.7 px, inside the training geometries


def register(sub):
    p = sub.add_parser(
        "demo",
        help="simulate turbulence on built-in sample images and write a labelled grid",
        description="Writes DIR/demo.png (rows: images; columns: clean | weak | medium | strong | depth and M), "
        "DIR/restore.png (input | restored | clean, with the recommended shipped model; predicted and true flow "
        "too for a model with a rectifier), "
        "DIR/demo_results.md (PSNR/SSIM per bin) and per-image PNGs.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_seed_arg(p)
    p.add_argument(
        "--weights",
        metavar="NAME|FILE",
        help="restoration model (default: the recommended shipped model, see d2turb models); 'none' skips restoration",
    )
    add_physics_args(p, path_length_m=DEMO_PATH_LENGTH_M)
    p.set_defaults(func=run)


def _label(tile, text):
    from PIL import ImageDraw

    draw = ImageDraw.Draw(tile)
    draw.rectangle((0, 0, 7 * len(text) + 6, 14), fill=(0, 0, 0))
    draw.text((3, 2), text, fill=(255, 255, 255))
    return tile


def run(args):
    # lazy: see d2turb.commands
    import numpy as np
    import torch
    from PIL import Image

    from d2turb.data.samples import sample_images
    from d2turb.depth import estimate_depth_prior
    from d2turb.device import resolve_device
    from d2turb.io import check_output_dir, to_uint8, write_image, write_json
    from d2turb.sim import Simulator, depth_modulation

    out = check_output_dir(args.out)
    images = sample_images()
    names = list(images)
    params = physics_params(args)
    sim = Simulator(params, device=resolve_device(args.device))
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
    rows, meta = [], {"params": params.to_dict(), "seed": args.seed, "levels": dict(LEVELS), "images": names}
    for i, name in enumerate(names):
        tiles = [_label(Image.fromarray(to_uint8(images[name])), "clean")]
        for k, (level, value) in enumerate(LEVELS):
            turb = res.turb[k * b + i]
            write_image(out / f"{name}_{level}_turb.png", turb)
            write_image(out / f"{name}_{level}_tilt.png", res.tilt[k * b + i])
            tiles.append(_label(Image.fromarray(to_uint8(turb)), f"{level} D/r0={value:g}"))
        d = to_uint8(depth[i, 0])
        m = to_uint8(modulation[i, 0])
        write_image(out / f"{name}_depth.png", depth[i])
        half = np.concatenate([d[:, : d.shape[1] // 2], m[:, d.shape[1] // 2 :]], axis=1)
        tiles.append(_label(Image.fromarray(half).convert("RGB"), "depth | M"))
        rows.append(np.concatenate([np.asarray(t) for t in tiles], axis=1))
    grid = np.concatenate(rows, axis=0)  # labels drawn on the tiles, unlike comparison_grid: the README's picture
    write_image(out / "demo.png", grid)
    print(f"wrote {out / 'demo.png'} ({len(names)} images x clean/weak/medium/strong/depth)")
    if args.weights != "none":
        # lazy: the restorer (models) loads only when restoration is asked for
        from d2turb.models.hub import recommended_weights, resolve_weights

        weights = args.weights
        try:
            weights = resolve_weights(weights) if weights is not None else recommended_weights()
        except D2TurbError as exc:
            if args.weights is not None:
                raise
            print(f"note: restoration skipped: {exc}")
        else:
            meta["restoration"] = restore_demo(weights, res, names, out, args.device)
    write_json(out / "demo_meta.json", meta)
    return 0


def restore_demo(weights, res, names: list[str], out, device) -> dict:
    """Restore every simulated image with ``weights``; write restore.png and demo_results.md; return the table.
    A model with a rectifier also gets predicted | true flow columns and the flow end-point errors."""
    # lazy: see d2turb.commands
    from d2turb.data.samples import SAMPLE_SIZE
    from d2turb.eval.metrics import KeyedMean, end_point_error, psnr, quantise_8bit, ssim
    from d2turb.eval.report import comparison_grid, flow_to_rgb
    from d2turb.io import write_image, write_text
    from d2turb.ops.splat import backward_flow
    from d2turb.restore import Restorer

    restorer = Restorer(weights, device=device)
    details = restorer.restore_with_details(res.turb.float().cpu())
    has_flow = bool(details["bwd_flow_px"].any())  # a plain restorer (no rectifier) predicts no flow
    true_flow = backward_flow(res.fwd_flow_px).float().cpu()
    gt = res.clean.float().cpu()
    b = len(names)
    rows, labels, table = [], [], {}
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
            row = [res.turb[j].float().cpu(), restored, gt[j]]
            if has_flow:
                peak = float(true_flow[j].norm(dim=0).max())
                row += [flow_to_rgb(details["bwd_flow_px"][j], peak), flow_to_rgb(true_flow[j], peak)]
            rows.append(row)
            labels.append(f"{name} {level}")
        means = mean.compute(level)
        keys = ["psnr_input", "psnr_restored", "ssim_input", "ssim_restored"]
        keys += ["epe_zero_flow_px", "epe_px"] if has_flow else []
        table[level] = {"dr0": value} | {key: means[key] for key in keys}
    columns = ["input", restorer.name, "clean"] + (["predicted flow", "true flow"] if has_flow else [])
    write_image(out / "restore.png", comparison_grid(rows, columns, labels, cell=SAMPLE_SIZE[1]))
    header = "| bin | D/r0 | PSNR input | PSNR restored | SSIM input | SSIM restored |"
    rule = "|---|---:|---:|---:|---:|---:|"
    if has_flow:
        header, rule = header + " EPE zero flow (px) | EPE (px) |", rule + "---:|---:|"
    lines = [
        f"# d2turb demo: restoration with {restorer.name}\n",
        f"{len(names)} built-in images per bin, {SAMPLE_SIZE[1]}x{SAMPLE_SIZE[0]} px "
        "(a demo, not a benchmark: see MODEL_CARD.md).\n",
        header,
        rule,
    ]
    for level, row in table.items():
        line = (
            f"| {level} | {row['dr0']:g} | {row['psnr_input']:.2f} | {row['psnr_restored']:.2f} | "
            f"{row['ssim_input']:.3f} | {row['ssim_restored']:.3f} |"
        )
        if has_flow:
            line += f" {row['epe_zero_flow_px']:.3f} | {row['epe_px']:.3f} |"
        lines.append(line)
    text = "\n".join(lines) + "\n"
    write_text(out / "demo_results.md", text)
    print(text, end="")
    print(f"wrote {out / 'restore.png'} ({' | '.join(columns)})")
    return {"weights": restorer.name, "table": table}
