# Sourced by experiments/table4_{hold,deadzone,search}.sh: the steps after a Table IV cell's
# `pointtrack select` (docs/table4.md, "Shipping"). Uses the caller's `world` array.

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
