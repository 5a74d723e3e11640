"""--config FILE.yaml and --set KEY=VALUE for eval and select (training.argconfig)."""

from __future__ import annotations

import pytest
import yaml

from training.argconfig import apply_config
from training.cli import build_parser, main


def _parse(argv: list[str]):
    parser = build_parser()
    args = parser.parse_args(argv)
    return apply_config(parser.command_parsers[args.command], args, lambda: parser.parse_args(argv))


@pytest.mark.parametrize("command", ["eval", "select"])
def test_precedence_defaults_file_flags_set(tmp_path, command):
    config = tmp_path / "c.yaml"
    config.write_text("preset: tiny\neval-seed: 3\nsetting: kitti-2\n")
    head = [command] if command == "eval" else [command, "p2b-kitti1-u"]
    args = _parse([*head, "--config", str(config)])
    assert (args.preset, args.eval_seed, args.setting) == ("tiny", 3, "kitti-2")  # file > default
    args = _parse([*head, "--config", str(config), "--eval-seed", "5"])
    assert (args.preset, args.eval_seed) == ("tiny", 5)  # a flag given beats the file
    args = _parse([*head, "--eval-seed", "5", "--config", str(config), "--set", "eval_seed=7"])
    assert args.eval_seed == 7  # --set beats both
    assert _parse(head).preset == build_parser().parse_args(head).preset != "tiny"  # defaults


def test_lists_and_switches_parse_as_their_flags(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(
        "tracker: [previous_box, constant_velocity]\neval_seeds: [0, 1]\nstrict: true\n"
    )
    args = _parse(["eval", "--config", str(config), "--set", "eval-seeds=2,3"])
    assert args.tracker == ["previous_box", "constant_velocity"]
    assert args.eval_seeds == [2, 3] and args.strict is True


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("presett: tiny\n", "unknown key 'presett'; valid: .*preset"),
        ("eval_seed: seven\n", "--eval-seed 'seven': invalid literal"),
        ("split: everything\n", "--split 'everything': must be one of train, val, test, all"),
        ("strict: 3\n", "--strict is a switch: give true or false, got 3"),
        ("- a list\n", "expected a mapping of options, got list"),
    ],
)
def test_a_bad_file_names_file_key_and_value(tmp_path, capsys, text, message):
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    assert main(["eval", "--config", str(config), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"pointtrack eval: --config {config}: ")
    assert __import__("re").search(message, err), err
    assert not (tmp_path / "out").exists()  # refused before any work


def test_bad_set_names_the_valid_keys(capsys):
    assert main(["eval", "--set", "nope=1"]) == 2
    assert "--set 'nope=1': expected KEY=VALUE with KEY one of " in capsys.readouterr().err


def test_eval_saves_its_options_and_they_reproduce_the_run(tmp_path, capsys):
    out_a, out_b = tmp_path / "a", tmp_path / "b"
    common = ["--preset", "tiny", "--split", "test", "--max-tracklets", "2", "--no-progress"]
    assert main(["eval", "--tracker", "previous_box", *common, "--out", str(out_a)]) == 0
    saved = yaml.safe_load((out_a / "config.yaml").read_text())
    assert saved["tracker"] == ["previous_box"] and saved["max_tracklets"] == 2
    assert "config_file" not in saved and "set_values" not in saved
    config = out_a / "config.yaml"
    assert main(["eval", "--config", str(config), "--set", f"out={out_b}"]) == 0
    report_a = yaml.safe_load((out_a / "report.json").read_text())
    report_b = yaml.safe_load((out_b / "report.json").read_text())
    assert report_a["previous_box"]["mean"] == report_b["previous_box"]["mean"]
    capsys.readouterr()
