"""The experiments/ scripts whose output goes into docs/ tables."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest


def _script(name: str):
    path = Path(__file__).parents[1] / "experiments" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(tmp_path: Path, name: str, epochs: dict[int, dict]) -> Path:
    run = tmp_path / name
    run.mkdir()
    rows = [{"kind": "data", "step": 0}]
    for epoch, values in epochs.items():
        rows.append({"kind": "train", "step": 50 * epoch - 40, "epoch": epoch, "total": 9.0})
        rows.append({"kind": "epoch", "epoch": epoch, "step": 50 * epoch, **values})
    (run / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return run


def test_epoch_losses_pairs_runs_by_epoch(tmp_path):
    script = _script("epoch_losses")
    a = _run(tmp_path, "slim", {1: {"total": 1.5, "vote": 0.25}, 2: {"total": 1.0, "vote": 0.125}})
    b = _run(tmp_path, "full", {1: {"total": 1.25, "vote": 0.5, "val_success": 12.34}})
    lines = script.table([a, b], ["total", "vote"], None).splitlines()
    assert lines[0] == (
        "| epoch | slim: total | slim: vote | slim: val | full: total | full: vote | full: val |"
    )
    # mean epoch losses, not the per-step "train" rows; blanks where a run has no such epoch
    assert lines[2] == "| 1 | 1.500 | 0.250 |  | 1.250 | 0.500 | 12.3 |"
    assert lines[3] == "| 2 | 1.000 | 0.125 |  |  |  |  |"
    assert len(script.table([a, b], ["total"], 1).splitlines()) == 3


def test_epoch_losses_names_a_run_without_a_log(tmp_path):
    script = _script("epoch_losses")
    with pytest.raises(SystemExit, match="nope/log.jsonl: no such file"):
        script.epoch_rows(tmp_path / "nope")
    empty = _run(tmp_path, "empty", {})
    with pytest.raises(SystemExit, match="no finished epoch yet"):
        script.epoch_rows(empty)
