# every movable task off CPU 0, then the loop's runs with both CPUs; restored after
moved=0
for p in $(ps -e -o pid=); do taskset -acp 1 $p >/dev/null 2>&1 && moved=$((moved+1)); done
echo "moved $moved" > /tmp/iso69/progress
cd /work/main && source .venv/bin/activate
for i in 1 2; do
 for v in pool-idle no-pool-idle; do
  taskset -c 0,1 python experiments/realtime.py --preset catching --eye truth --duration-s 30 --twin none --spin-us 1000 --$v --out /tmp/iso69/$v-$i > /tmp/iso69/$v-$i.log 2>&1
  echo "$v-$i $(date -u +%T)" >> /tmp/iso69/progress
 done
done
for p in $(ps -e -o pid=); do taskset -acp 0,1 $p >/dev/null 2>&1; done
echo done >> /tmp/iso69/progress
