# table of the real clips from real.log and real/*/measure.json (run from the scratch folder after real.sh)
import json
import os

print("| clip | frames | result | windows (D/r0 [90 %]) | consecutive windows overlap |")
print("|---|---|---|---|---|")
for block in open("real.log").read().split("== ")[1:]:
    name, _, rest = block.partition("\n")
    line = rest.strip().splitlines()[-1] if rest.strip() else "(not finished in this session)"
    key = {f"clear_hot_air/test{i}.mp4": f"test{i}" for i in range(1, 6)}.get(name, name)
    path = f"real/{key}/measure.json"
    if line.startswith("error") or not os.path.exists(path):
        what = "refused: " + line[7:] if line.startswith("error") else line
        print(f"| {name} | – | {what} | – | – |")
        continue
    r = json.load(open(path))
    ws = r.get("windows") or []
    wtxt = "; ".join(f"{w['dr0']:.2f} [{w['dr0_ci'][0]:.2f}, {w['dr0_ci'][1]:.2f}]" for w in ws)
    ov = [
        "yes" if a["dr0_ci"][1] >= b["dr0_ci"][0] and b["dr0_ci"][1] >= a["dr0_ci"][0] else "no"
        for a, b in zip(ws, ws[1:])
    ]
    lo, hi = r["dr0_ci"]
    head = f"D/r0 = {r['dr0']:.2f} [{lo:.2f}, {hi:.2f}], valid {100 * r['valid_fraction']:.0f} %"
    print(f"| {name} | {r['inputs']['frames']} | {head} | {wtxt} | {', '.join(ov)} |")
