#!/bin/bash
# The benchmark models' edits on one GPU (docs/benchmarks.md, fifty-third session; about 6 minutes
# on an H100): the CUDA tests, `crfedit eval edits --device cuda` on the four GPU-trained
# benchmark models (four at once, three CPU threads each), then the whole suite (pytest -n 14).
# Run on the device machine from the repository root with a cp312 OpenEXR wheel in .whl/, the
# models in runs/g_{p0,p1,r0,r1}.safetensors (benchmarks/gpu_models.sh) and both categories in
# runs/gpu/data.tar.xz (tar cJf runs/gpu/data.tar.xz -C runs real-chairs/chairs64 chairs8), since
# a lent machine takes 64 MiB at most. Results in $OUT: e_{p0,p1,r0,r1}.json and logs.txt.
# Compare them with the CPU's: python /work/diag21/summ.py, or `crfedit eval edits` here.
OUT=${OUT:?set OUT to a results folder}
source "$(dirname "$0")/gpu_setup.sh"
tar xJf runs/gpu/data.tar.xz -C runs || exit 1
echo "== CUDA tests $(date +%T)"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_device_resident.py 2>&1 | tail -4
echo "== eval edits on cuda $(date +%T)"
P=""
for k in p0 p1 r0 r1; do
    case $k in p*) data=runs/chairs8 ;; r*) data=runs/real-chairs/chairs64 ;; esac
    ( s=$(date +%s); OMP_NUM_THREADS=3 timeout 240 python3 -m crfedit eval edits runs/g_$k.safetensors $data \
        --strategies hybrid --no-nerf-baseline --json --seed 0 --device cuda > $OUT/e_$k.json 2> /tmp/e_$k.err
      echo "eval $k rc $? $(( $(date +%s)-s )) s"; tail -2 /tmp/e_$k.err ) &
    P="$P $!"
done
wait $P
echo "== suite $(date +%T)"
timeout 170 python3 -m pytest -q -n 14 -p no:cacheprovider tests 2>&1 | tail -15
date +%T
