# the real clips of docs/measure.md (run from a scratch folder; the d2turb on PYTHONPATH, else this checkout's src)
export PYTHONPATH=${PYTHONPATH:-$(cd "$(dirname "$0")/../.." && pwd)/src}
R=${REAL:-/work/shared/data/real}
for c in airport_heat_shimmer dost_street_1080p otis_door otis_tmt_text_inputs clear_hot_air; do
  echo "== $c"; python3 -m d2turb measure $R/$c --out real/$c --window 30 --plot 2>&1 | tail -1
done
for i in 1 2 3 4 5; do
  echo "== clear_hot_air/test$i.mp4"
  python3 -m d2turb measure $R/clear_hot_air/test$i.mp4 --out real/test$i --window 30 --plot 2>&1 | tail -1
done
