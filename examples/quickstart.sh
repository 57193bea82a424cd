#!/usr/bin/env bash
# The README's usage tour, end to end on CPU: procedural chairs → train → render → recolour a
# part from a twin's scribble and keep strokes → remove another on top → give another chair its
# colour code → inspect and bake the stack. Turntables of 24 views (the tour's have 36).
# Running it again in the same --work starts again: a new dataset, a new model, new edits.
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
value() {  # the value of option $1 ($2), refused in one line when missing or not of the form $3 (a regex)
    if [[ -z "${2-}" || ! "$2" =~ $3 ]]; then
        echo "error: $1 ${2-}: expected ${4}" >&2; exit 2
    fi
}
while [[ $# -gt 0 ]]; do
    case "$1" in
        --work) value "$1" "${2-}" '.' "a folder"; work="$2"; shift 2 ;;
        --minutes) value "$1" "${2-}" '^[0-9]*\.?[0-9]+$' "a number of minutes"; minutes="$2"; shift 2 ;;
        --instances) value "$1" "${2-}" '^[0-9]+$' "a whole number"; instances="$2"; shift 2 ;;
        --views) value "$1" "${2-}" '^[0-9]+$' "a whole number"; views="$2"; shift 2 ;;
        --res) value "$1" "${2-}" '^[0-9]+$' "a whole number of pixels"; res="$2"; shift 2 ;;
        -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
        *) echo "error: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
mkdir -p "$work"
data="$work/chairs" model="$work/chairs.safetensors"

# 1. A category of procedural chairs, with ground-truth edit twins and their scribbles.
crfedit dataset synth "$data" --instances "$instances" --views "$views" --res "$res"

# 2. One model over the category; prints held-out PSNR/SSIM at the end.
crfedit train "$data" --out "$model" --minutes "$minutes" --overwrite  # a model of this very dataset
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
print(spec.source, spec.view, root / spec.scribble, root / spec.keep, sep="\t")  # tabs: a --work with spaces
PY
}
IFS=$'\t' read -r source view scribble keep < <(twin color)
edit="$work/recolor.safetensors"
crfedit select "$model" --instance "$source" --view "$view" --scribble "$scribble" --keep "$keep" \
    --out "$work/part.sel.safetensors" --preview "$work/render/selection" --views orbit:8
crfedit edit-color "$model" --instance "$source" --view "$view" --scribble "$scribble" --keep "$keep" --color '#d03030' \
    --selection "$work/part.sel.safetensors" --out "$edit"
IFS=$'\t' read -r rsource rview rscribble rkeep < <(twin remove)
crfedit remove "$model" --instance "$rsource" --view "$rview" --scribble "$rscribble" --keep "$rkeep" --edit "$edit" \
    --out "$work/removed.safetensors" --preview "$work/render/removed" --views orbit:8

# 5. The edited chair from every side; then another chair takes its colour code (the code only:
#    the red lives in the recoloured chair's own F_rad, as the command's note says).
crfedit render "$model" --instance "$source" --edit "$edit" --views orbit:24 --out "$work/render/recolored" --video "$work/render/recolored.gif"
other=$(python -c "import sys; names = open(sys.argv[1]).read().split(); print(next(n for n in names if n != sys.argv[2]))" "$data/instances.txt" "$source")
crfedit transfer "$model" --instance "$other" --color-from "$source" --edit "$edit" --edit "$work/removed.safetensors" \
    --out "$work/colours.safetensors"

# 6. The edit file itself, and a model with the three edits baked in.
crfedit edits show "$edit"
crfedit edits bake "$model" --edit "$edit" --edit "$work/removed.safetensors" --edit "$work/colours.safetensors" \
    --out "$work/chairs-edited.safetensors" --overwrite
echo "done: renders in $work/render (orbit.gif, selection/, recolored.gif, removed/); $work/chairs-edited.safetensors"
