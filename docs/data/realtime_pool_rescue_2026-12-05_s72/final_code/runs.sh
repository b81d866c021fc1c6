#!/bin/bash
# the pool's watchdog on the 2-core VM: 15 s of catching with the truth eye at normal scheduling
# (--spin-us 1000), the loop on CPU 0; with 60 ms bursts of another process on CPU 0 every 2 s
# (benchmarks/cpu_bursts.py) and without; three arms alternated
cd /work/main
source .venv/bin/activate
for load in bursts quiet; do
 for rep in 1 2; do
  for arm in rescue norescue nopool; do
   case $arm in
    rescue) flag="--pool-idle";;
    norescue) flag="--pool-idle --pool-rescue-us None";;
    nopool) flag="--no-pool-idle";;
   esac
   [ $load = quiet ] && [ $arm = norescue ] && continue
   bp=
   if [ $load = bursts ]; then
     python benchmarks/cpu_bursts.py --cpu 0 --burst-ms 60 --every-s 2 --seconds 45 &
     bp=$!
   fi
   d=/tmp/s72/pr2/$load-$arm-$rep
   python experiments/realtime.py --preset catching --eye truth --duration-s 15 --twin none --spin-us 1000 $flag --out $d --overwrite > $d.log 2>&1
   [ -n "$bp" ] && { kill $bp 2>/dev/null; wait $bp 2>/dev/null; }
   echo "$load $arm $rep $(date +%H:%M:%S): $(grep -E 'deadline latency, every|missed 1 ms|rescued after' $d.log | sed 's/| deadline latency.*max \[us\] |//; s/| missed 1 ms deadlines (late + skipped) |//; s/| pool under.*end |//' | tr '\n' ' ')"
  done
 done
done
