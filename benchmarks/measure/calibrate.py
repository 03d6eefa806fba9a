# Calibration statistics of the clips matching a pattern (default "clips/cal*"): for each clip, the differential
# structure sums (d2turb.clip.strength.lag_sums) of the DIS flows and of the simulator's true flow (--save-flow) on the
# same pairs, separations 8–64 px, saved to calib/NAME.npz with the clip's truth, optics and registration
# diagnostics; and the same sums over windows of 16 and 32 frames of the clip's registration (keys num_dis_w32, …:
# (windows, tiles, J, T); what measure_clip(window=N) fits), for the clip term's dependence on the window length.
# A calib/NAME.npz without the window sums is redone. fitgain.py turns them into the registration gain and the
# interval's clip term.
import glob
import json
import os
import sys

import numpy as np

from d2turb.clip import motion
from d2turb.clip import strength as M
from d2turb.io import list_images, read_image

WINDOWS = (16, 32)
pattern = sys.argv[1] if len(sys.argv) > 1 else "clips/cal*"
os.makedirs("calib", exist_ok=True)
for d in sorted(glob.glob(pattern)):
    name = os.path.basename(d)
    out = f"calib/{name}.npz"
    if d.endswith((".err", ".lock")) or not os.path.exists(f"{d}/meta.json") or os.path.exists(f"{d}.lock"):
        continue  # not a clip, or still being simulated
    if os.path.exists(out) and "num_dis_w16" in np.load(out).files:
        continue
    meta = json.load(open(f"{d}/meta.json"))
    frames = [read_image(f) for f in list_images(f"{d}/turb")]
    true = np.stack([np.load(f) for f in sorted(glob.glob(f"{d}/flow/*.npy"))]).transpose(0, 2, 3, 1)
    gray, crop = motion.centre_crop(motion.gray_frames(frames), 320)
    flows, mask, diag = M.register_clip(gray)
    seps = [8, 16, 32, 64]
    nd, pd_, ser = M.lag_sums(flows, mask, seps)
    nt, pt, _ = M.lag_sums(true, mask, seps)
    info = {
        "clip": name,
        "image": meta["input"],
        "dr0": meta["dr0"],
        "aperture_m": meta["aperture_m"],
        "wavelength_m": meta["reference_wavelength_m"],
        "ifov_rad": meta["ifov_rad"],
        "path_length_m": meta["path_length_m"],
        "fps": meta["fps"],
        "wind_m_s": meta["wind_m_s"],
        **diag,
    }
    windows = {}
    for w in WINDOWS:
        for src, fl in (("dis", flows), ("true", true)):
            sums = [M.lag_sums(fl[s : s + w], mask, seps) for s in range(0, len(fl) - w + 1, w)]
            windows[f"num_{src}_w{w}"] = np.stack([a for a, _, _ in sums])
            windows[f"pairs_{src}_w{w}"] = np.stack([b for _, b, _ in sums])
    np.savez(out, num_dis=nd, pairs_dis=pd_, num_true=nt, pairs_true=pt, series=np.array(ser), info=json.dumps(info),
             **windows)  # fmt: skip
    print(json.dumps(info), flush=True)
