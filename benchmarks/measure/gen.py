# The simulated clips of the measure validation (docs/measure.md), from a scratch folder holding cal/ and img/
# (prep.py). `python3 gen.py` runs the clips still missing; several copies may run at once (each claims a clip by
# creating clips/NAME.lock). `python3 gen.py --list` prints the plan.
#   cal_X_i   calibration, default optics, bsds500 crops (cal/), i = 0…7: the registration gain and the interval's
#             scene term (fitgain.py)
#   calf_X_g  calibration, "field" geometry g of the bank (nine of its 16, footprints 4–31 px), bsds500 crops
#   calo_X_i, calof_X_g  calibration on outdoor photographs (calo/: camvid, strecha_mvs, sfm_landmarks crops, train
#             folders), default optics (i = 0…3) and four of the nine field geometries of calf_* per strength: the
#             scenes of use (low-texture outdoor views) in the clip-to-clip term (issue 28, third calibration)
#   val_X_i   validation, default optics (i ≤ 8: the first round, images alternating by strength; i ≥ 9: the other
#             scene type per strength, so that every strength has bsd100 and sunhays_outdoor crops)
#   valf_X_i  validation, "field" geometry bank (geometry (i + 4·cell) mod 16), scene types alternating; i = 0…15
#   (val_X_15, _16 and valf_X_13…15 came in a second batch, after vald_*, to reach ten measured clips per cell)
#   vald_X_i  validation, default optics with the depth prior (--depth prior), reported without a bar
#   calt_X_i  fourth calibration (issue 28): the 32 least textured train crops (calt/, prep.py), i = 0…7 per
#             strength, default optics for even i, a field geometry of calf_* for odd i; strength c gets crops
#             4·i + c of the texture ranking, so every strength sees the whole texture range
#   val_X_17…39, valf_X_16…39  a fourth validation batch, fixed before any of its clips was simulated: every cell
#             brought to 40 clips, scene types alternating, images of bsd100 (img/ and img2/) and sunhays_outdoor
#             never repeated within a cell (first unused in a per-cell rotation of each list)
#   calg_X_g_k  fifth calibration (issue 28): every geometry g of the field bank at D/r0 3.5 and 4.5, crops k = 0, 1
#             (cal5/, prep.py): the regime where the fourth validation's field 4.5 cell covered 76 % had 4
#             accepted calibration clips of footprint < 10 px
#   valn_X_i, valnf_X_i  a fresh validation set (after the fifth calibration), i = 0…31 per strength: new seeds, new
#             winds, the field geometry (5·i + 3·strength index) mod 16, scene types alternating, no image twice in a
#             cell; the 40-clip set above has informed four calibrations and is not used to judge the fifth
# All: 64 frames at 30 fps, boiling 0.1, wind 1–3 m/s, --save-flow, --no-mp4; --depth none except vald_*.
import glob
import json
import os
import subprocess
import sys

from d2turb.sim.geometry import geometry_bank

STRENGTHS = (1.5, 2.5, 3.5, 4.5)
BANK = geometry_bank("field")
CAL = sorted(glob.glob("cal/*.png"))
CALO = sorted(glob.glob("calo/*.png"))  # prep.py numbers them round robin over the three folders
CAL_FIELD = (8, 0, 13, 2, 14, 5, 15, 7, 9)  # the field geometries of calf_*
CALT = sorted(glob.glob("calt/*.png"))  # least textured first
CAL5 = sorted(glob.glob("cal5/*.png"))
BSD = sorted(glob.glob("img/*_SRF_2_HR.png"))
SUN = sorted(glob.glob("img/*_SRF_8_HR.png"))
OLD_VAL = sorted(BSD[:12] + SUN[:12])  # the first round's image list (indices below refer to it)


def wind(i, x):
    return round(1 + 2 * (((i * 7 + int(x) * 3) % 10) / 9), 2)


def field_args(g):
    p = BANK[g]
    return ["--aperture", repr(p.aperture_m), "--wavelength", repr(p.wavelength_m), "--ifov", repr(p.ifov_rad),
            "--path-length", repr(p.path_length_m)]  # fmt: skip


def plan():
    jobs = []  # (name, image, dr0, wind, seed, extra args)
    cal_new = iter(CAL[8:])
    for x in STRENGTHS:
        jobs.append((f"cal_{x}_0", CAL[int(x) % 8], x, wind(0, x), 1000 + int(x), []))
    cal_default = [(i, x) for i in range(1, 5) for x in STRENGTHS]
    field = [(g, x) for g in (8, 0, 13, 2, 14, 5) for x in STRENGTHS]  # footprints 4.2, 8.5, 16.3, 30.8, 5.7, 18.2 px
    for kind, i, x in [("d", *c) for c in cal_default[:4]] + [("f", *c) for c in field[:12]] + \
            [("d", *c) for c in cal_default[4:]] + [("f", *c) for c in field[12:]]:  # fmt: skip
        if kind == "d":
            jobs.append((f"cal_{x}_{i}", next(cal_new), x, wind(i, x), 2000 + 10 * (i - 1) + int(x), []))
        else:
            jobs.append((f"calf_{x}_{i}", next(cal_new), x, wind(i, x), 3000 + 10 * i + int(x), field_args(i)))
    # a second calibration batch (after the first validation: its clip-to-clip term rested on 8–11 clips per strength)
    for kind, i, x in [("d", i, x) for i in range(5, 8) for x in STRENGTHS] + [
        ("f", g, x)
        for g in (15, 7, 9)
        for x in STRENGTHS  # footprints 13.6, 7.3, 22.2 px
    ]:
        if kind == "d":
            jobs.append((f"cal_{x}_{i}", next(cal_new), x, wind(i, x), 2000 + 10 * (i - 1) + int(x), []))
        else:
            jobs.append((f"calf_{x}_{i}", next(cal_new), x, wind(i, x), 3000 + 10 * i + int(x), field_args(i)))
    # a third batch: outdoor scenes of the train folders, default optics and field geometries alternating
    calo = iter(CALO)
    for i in range(4):
        for c, x in enumerate(STRENGTHS):
            jobs.append((f"calo_{x}_{i}", next(calo), x, wind(i, x), 8000 + 10 * i + int(x), []))
            g = CAL_FIELD[(i + 4 * c) % len(CAL_FIELD)]
            jobs.append((f"calof_{x}_{g}", next(calo), x, wind(i + 5, x), 9000 + 10 * g + int(x), field_args(g)))
    bsd_new, sun_new = iter(BSD[12:]), iter(SUN[12:])
    rounds = []
    for i in range(9):
        rounds.append([(f"val_{x}_{i}", OLD_VAL[(i * 2 + int(x)) % 24], x, wind(i, x), i * 10 + int(x), [])
                       for x in STRENGTHS])  # fmt: skip
    for i in range(13):
        row = []
        for c, x in enumerate(STRENGTHS):
            img = next(bsd_new) if (i + c) % 2 == 0 else next(sun_new)
            row.append((f"valf_{x}_{i}", img, x, wind(i, x), 5000 + i * 10 + int(x), field_args((i + 4 * c) % 16)))
        if 9 + i < 15:  # six more default-optics clips per strength, of the scene type the first round lacked there
            for x in STRENGTHS:
                img = next(bsd_new) if int(x) % 2 == 1 else next(sun_new)
                row.append((f"val_{x}_{9 + i}", img, x, wind(9 + i, x), (9 + i) * 10 + int(x), []))
        rounds.append(row)
    for i in range(2):
        imgs = bsd_new if i == 0 else sun_new
        rounds.append([(f"vald_{x}_{i}", next(imgs), x, wind(i, x), 7000 + i * 10 + int(x), ["--depth", "prior"])
                       for x in STRENGTHS])  # fmt: skip
    for i in range(13, 16):  # a second batch: three more field clips and (i ≤ 14) two more default clips per strength
        row = []
        for c, x in enumerate(STRENGTHS):
            img = next(bsd_new) if (i + c) % 2 == 0 else next(sun_new)
            row.append((f"valf_{x}_{i}", img, x, wind(i, x), 5000 + i * 10 + int(x), field_args((i + 4 * c) % 16)))
        if i < 15:
            for x in STRENGTHS:
                img = next(bsd_new) if int(x) % 2 == 1 else next(sun_new)
                row.append((f"val_{x}_{i + 2}", img, x, wind(i + 2, x), (i + 2) * 10 + int(x), []))
        rounds.append(row)
    # the fourth calibration batch: low-texture train crops
    for i in range(8):
        for c, x in enumerate(STRENGTHS):
            extra = [] if i % 2 == 0 else field_args(CAL_FIELD[(i // 2 + 2 * c) % len(CAL_FIELD)])
            jobs.append((f"calt_{x}_{i}", CALT[4 * i + c], x, wind(i + 3, x), 6000 + 10 * i + int(x), extra))
    # the fourth validation batch: every cell to 40 clips
    old = [j for r in rounds for j in r]
    bsd_all, sun_all = BSD + sorted(glob.glob("img2/*.png")), SUN
    for c, x in enumerate(STRENGTHS):
        for kind, first in (("val", 17), ("valf", 16)):
            used = {j[1] for j in old if j[0].startswith(f"{kind}_{x}_")}
            shift = 13 * c + (7 if kind == "valf" else 0)
            pools = [bsd_all[shift:] + bsd_all[:shift], sun_all[shift:] + sun_all[:shift]]
            for i in range(first, 40):
                img = next(f for f in pools[(i + c) % 2] if f not in used)
                used.add(img)
                if kind == "val":
                    rounds.append([(f"val_{x}_{i}", img, x, wind(i, x), i * 10 + int(x), [])])
                else:
                    g = (i + 4 * c) % 16
                    rounds.append([(f"valf_{x}_{i}", img, x, wind(i, x), 5000 + i * 10 + int(x), field_args(g))])
    # the fifth calibration batch: strong turbulence on every field geometry
    cal5 = iter(CAL5)
    for k in range(2):
        for g in range(16):
            for x in (3.5, 4.5):
                jobs.append((f"calg_{x}_{g}_{k}", next(cal5), x, wind(g + k, x), 11000 + 1000 * k + 10 * g + int(x),
                             field_args(g)))  # fmt: skip
    # the fresh validation set
    for c, x in enumerate(STRENGTHS):
        for kind in ("valn", "valnf"):
            shift = 29 * c + (11 if kind == "valnf" else 3)
            pools = [bsd_all[shift:] + bsd_all[:shift], sun_all[shift:] + sun_all[:shift]]
            used = set()
            for i in range(32):
                img = next(f for f in pools[(i + c + 1) % 2] if f not in used)
                used.add(img)
                seed = 20000 + 1000 * (kind == "valnf") + 10 * i + int(x)
                extra = field_args((5 * i + 3 * c) % 16) if kind == "valnf" else []
                rounds.append([(f"{kind}_{x}_{i}", img, x, wind(i + 5, x), seed, extra)])
    return jobs + [j for r in rounds for j in r]


def run(job):
    name, img, x, w, seed, extra = job
    out = f"clips/{name}"
    if os.path.exists(f"{out}/meta.json"):
        return
    try:
        os.mkdir(f"{out}.lock")
    except FileExistsError:
        return
    depth = [] if "--depth" in extra else ["--depth", "none"]
    cmd = [sys.executable, "-m", "d2turb", "simulate-video", img, "--out", out, "--frames", "64", "--fps", "30",
           "--wind", str(w), "--boil", "0.1", "--dr0", str(x), "--save-flow", "--no-mp4", "--seed", str(seed),
           "--device", "cpu", *depth, *extra]  # fmt: skip
    with open(f"{out}.err", "w") as err:
        rc = subprocess.call(cmd, stdout=subprocess.DEVNULL, stderr=err)
    print(("done " if rc == 0 else "FAILED ") + name, flush=True)
    os.rmdir(f"{out}.lock")


if __name__ == "__main__":
    os.makedirs("clips", exist_ok=True)
    if "--list" in sys.argv:
        for j in plan():
            print(json.dumps(j))
    else:
        for j in plan():
            run(j)
