#!/bin/bash
# The paper's Tables 2 and 3 on the four GPU-trained benchmark models, on one GPU
# (docs/benchmarks.md, fifty-third session; about 5 minutes on an H100): `crfedit eval edits
# --strategies hybrid,codes,all` with the paper's method, four models at once (three CPU threads
# each), and the single-instance NeRF baseline on the two seed-0 models (the NeRFs do not depend
# on the category model, so the seed-1 models would train the same ones again).
# Run on the device machine from the repository root with a cp312 OpenEXR wheel in .whl/, the
# models in runs/g_{p0,p1,r0,r1}.safetensors (benchmarks/gpu_models.sh) and both categories in
# runs/gpu/data.tar.xz (tar cJf runs/gpu/data.tar.xz -C runs real-chairs/chairs64 chairs8).
# Results in $OUT: t_{p0,p1,r0,r1}.json (the eval's JSON) and logs.txt.
OUT=${OUT:?set OUT to a results folder}
LIMIT=${LIMIT:-420}
source "$(dirname "$0")/gpu_setup.sh"
tar xJf runs/gpu/data.tar.xz -C runs || exit 1
echo "== eval edits, all strategies, on cuda $(date +%T)"
P=""
for k in p0 p1 r0 r1; do
    case $k in p*) data=runs/chairs8 ;; r*) data=runs/real-chairs/chairs64 ;; esac
    case $k in *0) nerf=--nerf-baseline ;; *) nerf=--no-nerf-baseline ;; esac
    ( s=$(date +%s); OMP_NUM_THREADS=3 timeout $LIMIT python3 -m crfedit eval edits runs/g_$k.safetensors $data \
        --strategies hybrid,codes,all $nerf --json --seed 0 --device cuda > $OUT/t_$k.json 2> /tmp/t_$k.err
      echo "eval $k rc $? $(( $(date +%s)-s )) s"; grep -i "nerf\|error" /tmp/t_$k.err | tail -3 ) &
    P="$P $!"
done
wait $P
date +%T
