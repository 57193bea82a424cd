#!/bin/bash
# Two trainings sharing one GPU (docs/gpu.md, forty-seventh session; about 5.5 minutes on an H100).
#   A: both started together with crfedit's default threads and OMP_WAIT_POLICY=PASSIVE, 200 steps
#      (with libgomp's default, ACTIVE, their start-up ran 14x slower: each took every core);
#   B: both with OMP_NUM_THREADS=6, --minutes 4.5 to the end, a 10-s monitor of GPU use.
# Run on the device machine from the repository root, with a cp312 OpenEXR wheel in .whl/ and
# the real and procedural categories in runs/real-chairs/chairs64 and runs/chairs8; results in $OUT.
OUT=${OUT:?set OUT to a results folder}
source "$(dirname "$0")/gpu_setup.sh"
rm -rf /tmp/g_* /tmp/a_*
data() { [ "$1" = p ] && echo runs/chairs8 || echo runs/real-chairs/chairs64; }
mon() { while true; do echo "$(( $(date +%s)-T0 ))s $(nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader) $(for p in $(pgrep -f '^python3 -m crfedit train'); do ps -o stat=,pcpu=,nlwp= -p $p | tr -s ' '; done | tr '\n' ';')"; sleep "$1"; done; }
ms() { echo $(( ($(date +%s%N) - $1) / 1000000 )); }
P=""; echo "== A"; T0=$(date +%s); mon 5 > $OUT/monA.txt 2>&1 & M=$!
for k in r p; do
  ( s=$(date +%s%N); OMP_WAIT_POLICY=PASSIVE timeout 45 python3 -m crfedit train $(data $k) --out /tmp/a_$k.safetensors --steps 200 --device cuda --seed 0 --set part_labels=not-twins > $OUT/a_$k.log 2>&1; echo "A $k rc $? $(ms $s) ms" ) & P="$P $!"
done
wait $P; kill $M; wait 2>/dev/null
P=""; echo "== B"; T0=$(date +%s); mon 10 > $OUT/monB.txt 2>&1 & M=$!
for k in r p; do
  ( s=$(date +%s%N); OMP_NUM_THREADS=6 timeout 330 python3 -m crfedit train $(data $k) --out /tmp/g_$k.safetensors --minutes 4.5 --device cuda --seed 0 --set part_labels=not-twins > $OUT/train_$k.log 2>&1; echo "B $k rc $? $(ms $s) ms" ) & P="$P $!"
done
wait $P; kill $M; grep -ho '"threads": [0-9]*' /tmp/g_*.run.json
for k in r p; do tail -3 $OUT/train_$k.log; cp /tmp/g_$k.log.csv /tmp/g_$k.run.json $OUT/ 2>/dev/null
  python3 -m crfedit model strip /tmp/g_$k.safetensors --out $OUT/g_$k.safetensors; done
tail -4 $OUT/monB.txt
