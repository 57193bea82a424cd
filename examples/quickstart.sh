#!/usr/bin/env bash
# The README's usage tour, end to end on CPU: procedural chairs → train → render → recolour a
# part from a twin's scribble and keep strokes → remove another on top → inspect and bake.
#
#   examples/quickstart.sh [--work DIR] [--minutes M] [--instances N] [--views V] [--res R]
#
#   --work DIR       where everything goes (default runs/example)
#   --minutes M      training time (default 2)
#   --instances N    chairs in the category (default 8)
#   --views V        views per chair (default 20: 16 train / 2 val / 2 test)
#   --res R          image size (default 64)
#
# Run it from the repository root in the environment crfedit is installed in.
set -euo pipefail

work=runs/example minutes=2 instances=8 views=20 res=64
while [[ $# -gt 0 ]]; do
    case "$1" in
        --work) work="$2"; shift 2 ;;
        --minutes) minutes="$2"; shift 2 ;;
        --instances) instances="$2"; shift 2 ;;
        --views) views="$2"; shift 2 ;;
        --res) res="$2"; shift 2 ;;
        -h|--help) sed -n '2,13p' "$0"; exit 0 ;;
        *) echo "error: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
mkdir -p "$work"
data="$work/chairs" model="$work/chairs.safetensors"

# 1. A category of procedural chairs, with ground-truth edit twins and their scribbles.
crfedit dataset synth "$data" --instances "$instances" --views "$views" --res "$res"

# 2. One model over the category; prints held-out PSNR/SSIM at the end.
crfedit train "$data" --out "$model" --minutes "$minutes"
crfedit info "$model"

# 3. Renders of chair 0: its test views with depth, and a turntable.
crfedit render "$model" --instance chair_000 --views test --depth --out "$work/render/test"
crfedit render "$model" --instance chair_000 --views orbit:24 --out "$work/render/orbit" --video "$work/render/orbit.gif"

# 4. Recolor the part the first color twin scribbles, on the view it was drawn on: first see
#    what the scribble selects in 3-D (tinted previews), then edit.
twin() {  # source, view, scribble and keep strokes of the dataset's first twin of kind $1
    python - "$data" "$1" <<'PY'
import sys
from pathlib import Path

from crfedit.data.loading import read_twin_specs

root = Path(sys.argv[1])
spec = next(t for t in read_twin_specs(root) if t.kind == sys.argv[2])
print(spec.source, spec.view, root / spec.scribble, root / spec.keep)
PY
}
read -r source view scribble keep < <(twin color)
edit="$work/recolor.safetensors"
crfedit select "$model" --instance "$source" --view "$view" --scribble "$scribble" --keep "$keep" \
    --out "$work/part.sel.safetensors" --preview "$work/render/selection" --views orbit:8
crfedit edit-color "$model" --instance "$source" --view "$view" --scribble "$scribble" --keep "$keep" --color '#d03030' \
    --selection "$work/part.sel.safetensors" --out "$edit"
read -r rsource rview rscribble rkeep < <(twin remove)
crfedit remove "$model" --instance "$rsource" --view "$rview" --scribble "$rscribble" --keep "$rkeep" --edit "$edit" \
    --out "$work/removed.safetensors" --preview "$work/render/removed" --views orbit:8

# 5. The edited chair from every side, then the edit file itself and a model with it baked in.
crfedit render "$model" --instance "$source" --edit "$edit" --views orbit:24 --out "$work/render/recolored" --video "$work/render/recolored.gif"
crfedit edits show "$edit"
crfedit edits bake "$model" --edit "$edit" --out "$work/chairs-recolored.safetensors"
echo "done: renders in $work/render (orbit.gif, selection/, recolored.gif, removed/)"
