#!/bin/bash
# The four benchmark models trained side by side on one GPU (docs/benchmarks.md, forty-ninth
# session; about 8 minutes): procedural and real chairs, seeds 0 and 1, the CPU's 1024 rays a
# step, each for MINUTES of training (default 6.5), and tests/test_cuda.py alongside.
# Run on the device machine from the repository root, with a cp312 OpenEXR wheel in .whl/ and
# the categories in runs/chairs8 and runs/real-chairs/chairs64 (examples/real-chairs.sh
# --twin-sources 8 --data-only; crfedit dataset synth runs/chairs8 --twin-sources 8).
# Results in $OUT (six files at most come back from a lent machine): the stripped models
# g_{p,r}{0,1}.safetensors and logs.txt (the CUDA tests, each training's log tail and run.json, a GPU monitor).
OUT=${OUT:?set OUT to a results folder}
MINUTES=${MINUTES:-6.5}
DEVICE=${DEVICE:-cuda}  # DEVICE=cpu MINUTES=0.05: a smoke test of this script without a GPU
source "$(dirname "$0")/gpu_setup.sh"
T0=$(date +%s)
( while true; do echo "$(( $(date +%s)-T0 ))s $(nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null)"; sleep 15; done ) > /tmp/monitor.txt 2>&1 &
M=$!
( timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py > /tmp/cuda_tests.log 2>&1; echo "cuda tests rc $?" ) &
P="$!"
for k in p0 p1 r0 r1; do
    case $k in p*) data=runs/chairs8 ;; r*) data=runs/real-chairs/chairs64 ;; esac
    ( s=$(date +%s); OMP_NUM_THREADS=3 timeout $(python3 -c "print(int($MINUTES*60+90))") python3 -m crfedit train $data \
        --out /tmp/g_$k.safetensors --minutes $MINUTES --device $DEVICE --seed ${k:1} --set rays=1024 > /tmp/train_$k.log 2>&1
      echo "train $k rc $? $(( $(date +%s)-s )) s" ) &
    P="$P $!"
done
wait $P; kill $M
{
    echo "== tests/test_cuda.py"; tail -3 /tmp/cuda_tests.log
    for k in p0 p1 r0 r1; do echo "== $k"; tail -3 /tmp/train_$k.log; cat /tmp/g_$k.run.json; echo; done
    echo "== monitor (s since start, GPU use, memory)"; cat /tmp/monitor.txt
} > $OUT/logs.txt 2>&1
for k in p0 p1 r0 r1; do
    python3 -m crfedit model strip /tmp/g_$k.safetensors --out $OUT/g_$k.safetensors || cp /tmp/g_$k.safetensors $OUT/
done
grep -A2 '^== ' $OUT/logs.txt | grep -v '^{' | head -40
