#!/usr/bin/env bash
# nuScenes-A (docs/weather.md, "nuScenes-A"): the weather grid of every shipped
# p2b-nuscenes{1,2}-{u,w} file on the default-km nuScenes-layout test split (hdl32), each file
# in its own setting, then one table per setting. Resumable: a finished tracker's weather.json
# is kept. With ITEMS (SETTING=FILE pairs), those files instead of the shipped ones: the
# descriptive grid of the follow-up's selected, unshipped files (docs/weather.md, "nuScenes-A").
#   bash experiments/weather_nuscenes.sh [OUT]   # default runs/weather-nus
#   ITEMS="nuscenes-1=a.safetensors nuscenes-2=b.safetensors" bash experiments/weather_nuscenes.sh OUT
set -euo pipefail
out=${1:-runs/weather-nus}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
# the scene frame every nuScenes file since the scene-frame pilot trained in (docs/table4.md);
# --strict refuses a file trained in another frame, or on the test split, rather than warning
world=(--dataset nuscenes --preset default-km --sensor hdl32 --nuscenes-frame scene --seed 0
  --split test --strict)

grid() {  # SETTING TRACKER NAME: TRACKER's grid into OUT/SETTING/NAME
  local dir="$out/$1/$3"
  if compgen -G "$dir/weather_*/weather.json" > /dev/null; then return; fi
  pointtrack eval --tracker "$2" "${world[@]}" --setting "$1" --weather all --no-analysis \
    --workers 2 --no-progress --out "$dir" < /dev/null > "$out/$1-$3.log" 2>&1
}

trackers_of() {  # N: the trackers of nuscenes-N, from ITEMS or the shipped files
  local item name
  if [ -n "${ITEMS:-}" ]; then
    for item in $ITEMS; do
      if [ "${item%%=*}" = "nuscenes-$1" ]; then echo "${item#*=}"; fi
    done
    return
  fi
  for name in p2b-nuscenes$1-u p2b-nuscenes$1-w; do
    if [ -e "trackers/checkpoints/$name.safetensors" ]; then  # else not shipped (table4.md)
      echo "$name"
    fi
  done
}

mkdir -p "$out"
for n in 1 2; do
  items=()
  while read -r tracker; do
    name=$(basename "$tracker" .safetensors)
    grid "nuscenes-$n" "$tracker" "$name"
    items+=("$name=$(compgen -G "$out/nuscenes-$n/$name/weather_*/weather.json")")
  done < <(trackers_of "$n")
  if [ "${#items[@]}" -gt 0 ]; then
    PYTHONPATH=$PWD python experiments/weather_tables.py "${items[@]}" \
      --table "$out/nuscenes-$n.txt" --groups observed unseen
  fi
done
