#!/usr/bin/env bash
# Real chairs, end to end: Debian's Sweet Home 3D furniture catalogs → a category of real chair
# meshes rendered at 64×64 → train → evaluate reconstruction → recolor one chair → render it.
#
#   examples/real-chairs.sh [--work DIR] [--count N] [--views V] [--twin-sources T] [--hires] [--data-only]
#
#   --work DIR    where everything goes (default runs/real-chairs)
#   --count N     chairs in the category (default 24; the catalogs hold 47 with 2+ parts)
#   --views V     views per chair (default 50: 40 train / 5 val / 5 test)
#   --twin-sources T  chairs per twin kind with a ground-truth twin (default 4; 8: the 16-twin benchmark)
#   --hires       also build the category at 128×128 (DIR/chairs128)
#   --data-only   stop once the data is built (no training)
#
# TRAIN_ARGS (environment) is passed on to `crfedit train` (default "--minutes 10"). Run again
# in the same --work, the script builds the data again and trains a new model (--overwrite),
# unless TRAIN_ARGS holds --resume (then it goes on training the one there).
# Needs the [meshes] extra (trimesh, embreex); installs it when missing.  The furniture package
# is installed with apt-get when run as root, else downloaded and unpacked into DIR/debian.
# The models are CC-BY 3.0 / CC0: DIR/chairs64/ATTRIBUTION.txt lists model, creator, license
# and source of every chair — keep it with the data and with anything rendered from it.
set -euo pipefail

work=runs/real-chairs count=24 views=50 twin_sources=4 hires=0 data_only=0
while [[ $# -gt 0 ]]; do
    case "$1" in
        --work) work="$2"; shift 2 ;;
        --count) count="$2"; shift 2 ;;
        --views) views="$2"; shift 2 ;;
        --twin-sources) twin_sources="$2"; shift 2 ;;
        --hires) hires=1; shift ;;
        --data-only) data_only=1; shift ;;
        -h|--help) sed -n '2,18p' "$0"; exit 0 ;;
        *) echo "error: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
for n in "$count" "$views" "$twin_sources"; do
    [[ "$n" =~ ^[1-9][0-9]*$ ]] || { echo "error: --count, --views and --twin-sources take whole numbers of at least 1 (got $n)" >&2; exit 2; }
done
mkdir -p "$work"

# 1. The Sweet Home 3D furniture catalogs (.sh3f zips of OBJ + MTL models).
catalogs=/usr/share/sweethome3d/furniture
if ! ls "$catalogs"/*.sh3f >/dev/null 2>&1; then
    if [[ $(id -u) -eq 0 ]]; then
        apt-get install -y sweethome3d-furniture || { apt-get update && apt-get install -y sweethome3d-furniture; }
    else
        (cd "$work" && apt-get download sweethome3d-furniture)
        dpkg -x "$work"/sweethome3d-furniture_*.deb "$work/debian"
        catalogs="$work/debian/usr/share/sweethome3d/furniture"
    fi
fi

python -c "import trimesh, embreex" 2>/dev/null || python -m pip install --quiet 'trimesh>=4' 'embreex>=2.17'

# 2. Pick the chairs (name says chair/armchair, upright proportions, 2+ materials) and extract
#    each as meshes/<name>/<name>.obj + MTL + textures + <name>.meta.json (attribution, rotation).
# The folder is this script's own (it marks it): a meshes/ folder of anything else is refused, not deleted.
ours() {  # marked, or (made before the mark) every entry a chair folder with the meta.json this script writes
    [[ -e "$1/.real-chairs" ]] || python -c "import pathlib, sys; p = pathlib.Path(sys.argv[1]); sys.exit(0 if p.is_dir() and all(d.is_dir() and any(d.glob('*.meta.json')) for d in p.iterdir()) else 1)" "$1"
}
if [[ -e "$work/meshes" ]] && ! ours "$work/meshes"; then
    echo "error: $work/meshes exists and was not made by this script; move it, or give another --work" >&2
    exit 2
fi
rm -rf "$work/meshes"
python - "$catalogs" "$work/meshes" "$count" <<'EOF'
import sys
from pathlib import Path

from crfedit.data.sh3f import debian_catalogs, extract_model, pick_chairs

catalogs, out, count = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
chairs = pick_chairs(debian_catalogs(catalogs), count)
for chair in chairs:
    obj = extract_model(chair, out)
    print(f"  {obj.stem:<40} {chair.name} by {chair.creator} ({chair.catalog.name})")
print(f"extracted {len(chairs)} chairs to {out}" + (f" (the catalogs hold {len(chairs)} such chairs, not {count})" if len(chairs) < count else ""))
(out / ".real-chairs").write_text("made by examples/real-chairs.sh: replaced whole on its next run\n")
EOF

# 3. Render the category: parts = material groups, random part colors, depth + part maps, twins.
data="$work/chairs64"
crfedit dataset from-meshes "$data" "$work"/meshes/*/*.obj --up y --views "$views" --res 64 --twin-sources "$twin_sources"
if [[ $hires -eq 1 ]]; then
    crfedit dataset from-meshes "$work/chairs128" "$work"/meshes/*/*.obj --up y --views "$views" --res 128 --twin-sources "$twin_sources"
fi
crfedit dataset info "$data"
[[ $data_only -eq 1 ]] && exit 0

# 4. Train one model over the category; evaluate its reconstruction and the twin edits.
model="$work/model64.safetensors"
train_args=${TRAIN_ARGS:---minutes 10}
[[ " $train_args " == *" --resume "* ]] || train_args="$train_args --overwrite"  # a re-run: a model of this very data
# shellcheck disable=SC2086  # TRAIN_ARGS is a list of options
crfedit train "$data" --out "$model" $train_args
crfedit eval recon "$model" "$data"
crfedit eval edits "$model" "$data"     # the paper's protocol on the real chairs' twins

# 5. Recolor one chair: the first color twin gives the chair, the scribbled view, the scribble
#    and the keep strokes (what must not change).
IFS=$'\t' read -r instance view scribble keep < <(python - "$data" <<'EOF'
import sys
from pathlib import Path

from crfedit.data.loading import instance_names, read_twin_specs

root = Path(sys.argv[1])
spec = next(t for t in read_twin_specs(root) if t.kind == "color")
print(instance_names(root).index(spec.source), spec.view, root / spec.scribble, root / spec.keep, sep="\t")  # tabs: a --work with spaces
EOF
)
edit="$work/recolor.safetensors"
crfedit edit-color "$model" --instance "$instance" --view "$view" --scribble "$scribble" --keep "$keep" --color '#d03030' --out "$edit"
crfedit render "$model" --instance "$instance" --edit "$edit" --views orbit:8 --out "$work/recolored"
echo "done: renders of the recolored chair in $work/recolored; attribution in $data/ATTRIBUTION.txt"
