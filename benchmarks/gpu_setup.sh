# Sourced by the gpu_*.sh scripts on a lent machine, from the repository root: unbuffered
# Python; the carried cp312 OpenEXR wheel (.whl/) installed where the machine lacks OpenEXR;
# the repository on PYTHONPATH; then what the machine is (GPU, torch, CPU).
export PYTHONUNBUFFERED=1
if ! python3 -c "import OpenEXR" 2>/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH} || exit 1
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
nvidia-smi --query-gpu=name,memory.total,clocks.sm,temperature.gpu --format=csv,noheader 2>/dev/null
python3 -c "import torch, numpy, typer; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__, 'typer', typer.__version__)"
lscpu | grep -m1 'Model name'
