#!/bin/bash
# Run from a scratch folder (here /work/exp_measure) holding cal/ and img/: 256² centre crops of the first 8 bsds500
# images (calibration) and of the first 12 bsd100 + 12 sunhays_outdoor images of the fixed split (validation).
# simulated clips for calibration (bsds500 crops, cal/) and validation (bsd100 + sunhays_outdoor crops, img/)
export PYTHONPATH=/work/wt/measure/src
cd /work/exp_measure
CAL=(cal/*.png); VAL=(img/*.png)
gen() { # out img dr0 wind seed
  [ -f $1/meta.json ] && return
  d2turb simulate-video $2 --out $1 --frames 64 --fps 30 --wind $4 --boil 0.1 --dr0 $3 --depth none --save-flow --no-mp4 --seed $5 >/dev/null 2>$1.err || echo fail $1
}
for i in 0; do for x in 1.5 2.5 3.5 4.5; do
  j=$(( (i*4 + ${x%.*}) % 8 )); w=$(python3 -c "print(round(1+2*((($i*7+${x%.*}*3)%10)/9),2))")
  gen clips/cal_${x}_$i ${CAL[$j]} $x $w $((1000+i*10+${x%.*}))
done; done
for i in $(seq 0 11); do for x in 1.5 2.5 3.5 4.5; do
  # alternate bsd100 (SRF_2) and sunhays (SRF_8) images; wind spread over 1..3 m/s
  k=$(( (i*2 + ${x%.*}) % 24 )); w=$(python3 -c "print(round(1+2*((($i*7+${x%.*}*3)%10)/9),2))")
  gen clips/val_${x}_$i ${VAL[$k]} $x $w $((i*10+${x%.*}))
done; done
echo done
