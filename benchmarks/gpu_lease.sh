#!/bin/bash
# One GPU lease's checks in one call (about 7 minutes on an H200): CUDA tests, the suite, edits on CUDA, benchmarks/gpu.py.
# Run on the device machine from the repository root, with a cp312 OpenEXR wheel in .whl/ and
# the 24-chair category in runs/bench/chairs (see docs/gpu.md); results go to $OUT.
source "$(dirname "$0")/gpu_setup.sh"
echo "== CUDA tests"; date +%T
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_device_resident.py "tests/test_cli_train_render.py::test_render_files_sizes_depth_and_determinism" 2>&1 | tee $OUT/cuda_tests.log | tail -8
echo "== suite"; date +%T
timeout 220 python3 -m pytest -q -n 14 -p no:cacheprovider tests 2>&1 | tee $OUT/suite.log | tail -12
echo "== train + eval edits on cuda"; date +%T
timeout 60 python3 -m crfedit train runs/bench/chairs --minutes 0.3 --device cuda --seed 0 --out $OUT/m.safetensors 2>&1 | tail -3
timeout 120 python3 -m crfedit eval edits $OUT/m.safetensors runs/bench/chairs --strategies hybrid --no-nerf-baseline --json --device cuda > $OUT/edits_cuda.json 2> $OUT/edits_cuda.err; echo "rc $?"; tail -3 $OUT/edits_cuda.err
echo "== gpu.py"; date +%T
timeout 230 python3 benchmarks/gpu.py --data runs/bench/chairs --rays 1024,8192,65536 --minutes 0.4 --checkpoints 5 --md $OUT/benchmarks.md --json $OUT/gpu.json 2>&1 | tail -25
date +%T
