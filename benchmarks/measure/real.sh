export PYTHONPATH=/work/wt/measure/src
R=/work/shared/data/real
for c in airport_heat_shimmer dost_street_1080p otis_door otis_tmt_text_inputs clear_hot_air; do
  echo "== $c"; d2turb measure $R/$c --out real/$c --window 30 --plot 2>&1 | tail -1
done
for i in 1 2 3 4 5; do echo "== clear_hot_air/test$i.mp4"; d2turb measure $R/clear_hot_air/test$i.mp4 --out real/test$i --window 30 --plot 2>&1 | tail -1; done
