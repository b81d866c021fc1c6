#!/bin/bash
# alternated: 60 ms bursts every 2 s on CPU 0, 15 s catching with the truth eye
cd /work/main
for rep in 1 2; do
 for arm in hold0 hold20 nopool; do
  case $arm in
   hold0) env="HEC_RESCUE_HOLD_MS=0"; flag="--pool-idle";;
   hold20) env="HEC_RESCUE_HOLD_MS=20"; flag="--pool-idle";;
   nopool) env=""; flag="--no-pool-idle";;
  esac
  python benchmarks/cpu_bursts.py --cpu 0 --burst-ms 60 --every-s 2 --seconds 45 &
  bp=$!
  env $env python experiments/realtime.py --preset catching --eye truth --duration-s 15 --twin none --spin-us 1000 $flag --out /tmp/s72/ab_${arm}_$rep --overwrite > /tmp/s72/ab_${arm}_$rep.log 2>&1
  kill $bp 2>/dev/null; wait $bp 2>/dev/null
  echo "$arm $rep: $(grep -E 'deadline latency, every|missed 1 ms|rescued after' /tmp/s72/ab_${arm}_$rep.log | tr '\n' ' ')"
 done
done
