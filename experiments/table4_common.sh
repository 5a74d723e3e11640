# Sourced by experiments/table4_{hold,deadzone,search}.sh: the steps after a Table IV cell's
# `pointtrack select` (docs/table4.md, "Shipping"). Uses the caller's `world` array.

select_once() {  # OUT NAME SETTING LOG CANDIDATE...: `pointtrack select` on the never-trained
  # worlds into OUT, the first-ranked file saved as OUT/NAME.safetensors; kept once written (a
  # baseline ranked first has no file to save: the ranking stands, the script goes on)
  local out=$1 name=$2 setting=$3 log=$4
  shift 4
  if [ ! -e "$out/selection.json" ]; then
    pointtrack select "$@" --setting "$setting" "${world[@]}" --train-world 0 --no-progress \
      --out "$out" --save "$out/$name.safetensors" > "$log" 2>&1 \
      || grep -q "is not a tracker file" "$log"
  fi
}

first_ranked() {  # SELECTION_JSON -> its first-ranked candidate
  python -c "import json,sys; print(json.load(open(sys.argv[1]))['ranking'][0]['candidate'])" "$1"
}

test_name() {  # CANDIDATE -> the name its test reading is filed under: a RUN/best.pt's run
  # folder, a file's stem (as experiments/table4_ship.py's selected_run reads it)
  case $1 in
    *.pt) basename "$(dirname "$1")" ;;
    *) basename "$1" .safetensors ;;
  esac
}

read_test_once() {  # ROOT CANDIDATE SETTING: its one reading on world 0 test, eval seeds 0-2,
  # in ROOT/test/NAME (kept: a rerun reads nothing again)
  local name
  name=$(test_name "$2")
  if [ ! -e "$1/test/$name/done" ]; then
    pointtrack eval --tracker "$2" "${world[@]}" --seed 0 --split test --setting "$3" \
      --eval-seeds 0 1 2 --no-progress --out "$1/test/$name" > "$1/logs/eval-$name.log" 2>&1
    touch "$1/test/$name/done"
  fi
}
