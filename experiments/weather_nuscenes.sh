#!/usr/bin/env bash
# nuScenes-A (docs/weather.md, "nuScenes-A"): the weather grid of every shipped
# p2b-nuscenes{1,2}-{u,w} file on the default-km nuScenes-layout test split (hdl32), each file
# in its own setting, then one table per setting. Resumable: a finished tracker's weather.json
# is kept.
#   bash experiments/weather_nuscenes.sh [OUT]   # default runs/weather-nus
set -euo pipefail
out=${1:-runs/weather-nus}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
world=(--dataset nuscenes --preset default-km --sensor hdl32 --seed 0 --split test)

grid() {  # SETTING TRACKER
  local dir="$out/$1/$2"
  if [ -e "$dir/weather_$2/weather.json" ]; then return; fi
  pointtrack eval --tracker "$2" "${world[@]}" --setting "$1" --weather all --no-analysis \
    --workers 2 --no-progress --out "$dir" > "$out/$1-$2.log" 2>&1
}

mkdir -p "$out"
for n in 1 2; do
  items=()
  for name in p2b-nuscenes$n-u p2b-nuscenes$n-w; do
    if [ ! -e "trackers/checkpoints/$name.safetensors" ]; then
      continue  # not shipped (docs/table4.md, "Shipping")
    fi
    grid "nuscenes-$n" "$name"
    items+=("$name=$out/nuscenes-$n/$name/weather_$name/weather.json")
  done
  if [ "${#items[@]}" -gt 0 ]; then
    PYTHONPATH=$PWD python experiments/weather_tables.py "${items[@]}" \
      --table "$out/nuscenes-$n.txt" --groups observed unseen
  fi
done
