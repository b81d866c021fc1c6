#!/bin/bash
cd /work/main; source .venv/bin/activate
for rep in 1 2 3; do
 for arm in final quiet; do
  e=""; [ $arm = quiet ] && e="HEC_RESCUE_QUIET=1"
  python benchmarks/cpu_bursts.py --cpu 0 --burst-ms 60 --every-s 2 --seconds 45 &
  bp=$!
  d=/tmp/s72/q/$arm-$rep
  env $e python experiments/realtime.py --preset catching --eye truth --duration-s 15 --twin none --spin-us 1000 --pool-idle --out $d --overwrite > $d.log 2>&1
  kill $bp 2>/dev/null; wait $bp 2>/dev/null
  echo "$arm $rep: $(grep -E 'deadline latency, every|missed 1 ms|rescued after' $d.log | sed 's/| deadline latency.*max \[us\] |//; s/| missed 1 ms deadlines (late + skipped) |//; s/| pool under.*end |//' | tr '\n' ' ')"
 done
done
