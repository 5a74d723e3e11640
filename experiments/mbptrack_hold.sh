#!/usr/bin/env bash
# The still-target test on the shipped MBPTrack files (docs/mbptrack.md, "Still-target test on
# the shipped files"): per arm, the shipped file, its hold variants (hold_chamfer_m 0.15 / 0.20)
# and previous_box ranked by `pointtrack select` on the never-trained parts of `default`; a
# variant ranked first replaces the shipped file (recipe + back-fill) and gets the one test
# reading (world 0 test, eval seeds 0-2). Resumable: finished steps are kept. NAMES: the
# shipped files to test (default the two slim files; `mbptrack-kitti1-u-light`, docs/mbptrack.md
# "A `light` size", is recorded as made by experiments/mbptrack_light.sh).
#   bash experiments/mbptrack_hold.sh [ROOT]    # default runs/mbptrack-hold; WORKERS (default 2)
#   NAMES=mbptrack-kitti1-u-light bash experiments/mbptrack_hold.sh runs/mbptrack-light-hold
set -euo pipefail
root=${1:-runs/mbptrack-hold}
workers=${WORKERS:-2}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset synthetic --preset default)
source "$(dirname "$0")/table4_common.sh"  # first_ranked, read_test_once (on world 0 test)
read -r -a names <<< "${NAMES:-mbptrack-kitti1-u mbptrack-kitti1-w}"
mkdir -p "$root/logs" "$root/hold" "$root/test"

for name in "${names[@]}"; do
  arm=${name#mbptrack-kitti1-}  # u, w or u-light: the folders' and logs' names
  case $name in  # the script and runs folder that made the shipped file
    *-light) origin=(mbptrack_light.sh /work/runs/mbptrack-light) ;;
    *) origin=(mbptrack_ship.sh /work/runs/mbptrack-ship) ;;
  esac
  mapfile -t variants < <(python3 experiments/hold_variants.py "$name" --holds 0.15 0.2 \
    --out "$root/hold")
  out=$root/select-$arm
  if [ ! -e "$out/selection.json" ]; then
    pointtrack select "$name" "${variants[@]}" previous_box --setting kitti-1 \
      --workers "$workers" --no-progress --out "$out" --save "$out/$name.safetensors" \
      > "$root/logs/select-$arm.log" 2>&1
  fi
  first=$(first_ranked "$out/selection.json")
  if [ "$first" = "$name" ] || [ "$first" = previous_box ]; then continue; fi
  read_test_once "$root" "$first" kitti-1
  # the recipe: the shipped file's own command, then this one
  python3 experiments/mbptrack_ship.py ship "$out" "$name" \
    --command "bash experiments/${origin[0]} ${origin[1]}" \
    --command "NAMES=$name bash experiments/mbptrack_hold.sh $root" --not-if "$name" previous_box \
    --runs "${origin[1]}, $root"
done
python3 scripts/backfill_provenance.py
