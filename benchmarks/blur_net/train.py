"""Train the learned blur estimate (``d2turb.clip.blur_net``) on cached fused frames of simulated clips (cache.py).

    python benchmarks/blur_net/train.py --data CACHE_DIRS... --out blur-net.safetensors [--steps 6000]

Each sample: the fused frame's 2K most textured patches (K drawn at random, rotated/flipped: the blur is
isotropic), the tilt spread of its registered frame, the targets of ``blur_targets``. Loss: squared error for the
first fifth of the steps, then the Gaussian negative log-likelihood (the log-variances learn the spread). A tenth of
the clips is held out and its median absolute error printed. One thread, seed 0.
"""

import argparse
import glob
import io
import random
import time

import numpy as np
import torch
from PIL import Image

from d2turb.clip.blur_net import BlurNet, blur_targets, textured_patches, tilt_spread
from d2turb.models.weights import save_pretrained

# sharp samples: a clip's clean frame with camera noise (σ 0–3 grey) and JPEG (quality 75–95), no blur, taught as
# the unblurred end of the family (M = 0.1, λ/(D·ifov) 0.7 px, D/r0 1: an OTF ≥ 0.9 everywhere); their tilt
# spread drawn from the low end of the clips' (0.6–1.4 px)
SHARP_TARGET = (1.0, 0.7, 0.1)


def sharp_frame(gt: np.ndarray, rng: random.Random) -> np.ndarray:
    img = gt.transpose(1, 2, 0) * 255 + rng.uniform(0, 3) * np.random.default_rng(
        rng.randrange(1 << 30)
    ).standard_normal(gt.shape[1:] + (3,))
    buf = io.BytesIO()
    Image.fromarray(np.clip(np.rint(img), 0, 255).astype(np.uint8)).save(buf, "JPEG", quality=rng.randint(75, 95))
    return np.asarray(Image.open(buf), np.float32).transpose(2, 0, 1) / 255


def load(dirs, k, sharp_share):
    samples = []
    rng = random.Random(1)
    for d in dirs:
        for f in sorted(glob.glob(f"{d}/*.npz")):
            z = np.load(f)
            y = blur_targets(float(z["dr0"]), float(z["lod"]), float(z["m"]))
            for j in range(z["fused"].shape[0]):
                p = textured_patches(z["fused"][j].astype(np.float32), 2 * k)
                samples.append((p, tilt_spread(z["flow"][j]), y, f))
            if rng.random() < sharp_share:
                p = textured_patches(sharp_frame(z["gt"].astype(np.float32), rng), 2 * k)
                samples.append((p, rng.uniform(-0.5, 0.34), blur_targets(*SHARP_TARGET), f))
    return samples


def batch(items, k, rnd):
    ps, ts, ys = [], [], []
    for p, t, y, _ in items:
        sel = p[sorted(random.sample(range(len(p)), min(k, len(p))))] if rnd else p[:k]
        if rnd:
            sel = np.rot90(sel, random.randint(0, 3), axes=(1, 2))
            sel = sel[:, :, ::-1] if random.random() < 0.5 else sel
        ps.append(np.ascontiguousarray(sel))
        ts.append(t)
        ys.append(y)
    return torch.from_numpy(np.stack(ps)), torch.tensor(ts), torch.stack(ys)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--patches", type=int, default=8)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--no-tilt", action="store_true")
    ap.add_argument("--sharp-share", type=float, default=0.15, help="clips that also give a sharp sample")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    random.seed(0)
    samples = load(args.data, args.patches, args.sharp_share)
    clips = sorted({s[3] for s in samples})
    random.shuffle(clips)
    hold = set(clips[: len(clips) // 10])
    train = [s for s in samples if s[3] not in hold]
    val = [s for s in samples if s[3] in hold]
    print(len(train), "training samples,", len(val), "held out", flush=True)
    net = BlurNet(args.width, args.patches, tilt=not args.no_tilt)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.steps, pct_start=0.1)

    def held_out():
        net.eval()
        with torch.no_grad():
            err = torch.cat(
                [
                    (
                        net(*batch(val[i : i + 64], args.patches, False)[:2])[0]
                        - batch(val[i : i + 64], args.patches, False)[2]
                    ).abs()
                    for i in range(0, len(val), 64)
                ]
            )
        net.train()
        return err.median(0).values.numpy().round(3)

    t0 = time.time()
    for step in range(args.steps):
        p, t, y = batch(random.sample(train, args.batch), args.patches, True)
        mu, log_var = net(p, t)
        if step < args.steps // 5:
            loss = ((mu - y) ** 2).mean()
        else:
            loss = (0.5 * ((mu - y) ** 2 * torch.exp(-log_var) + log_var)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 500 == 0 or step == args.steps - 1:
            print(f"{step} {time.time() - t0:.0f}s loss {loss.item():.3f} held-out median |err| "
                  f"(ln D/r0, ln λ/(D·ifov), logit M) {held_out()}", flush=True)  # fmt: skip
    save_pretrained(net.eval(), args.out)


if __name__ == "__main__":
    main()
