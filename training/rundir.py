"""Run directories and the files in them: the one place for what ``pointtrack train`` and
``pointtrack finetune`` (and the reports of ``eval`` / ``select``) do on disk.

* **Atomic writes**: :func:`atomic_path` (a context manager: write the yielded temporary sibling
  ``.NAME.tmpPID`` by any means, it is flushed to disk with ``fsync`` and renamed into place),
  :func:`atomic_write_text`, :func:`atomic_write_bytes` and :func:`atomic_save_safetensors`
  (every safetensors file), defined in :mod:`envs.files` (the
  env's pictures use them too) and re-exported here. A killed process leaves either the
  previous file or the new one, never a truncated one; :func:`remove_stale_temps` deletes the
  temporaries of dead processes.
* **Run directories**: :func:`prepare_run_dir` decides, before any data is built, whether a run
  into a directory starts fresh, resumes or replaces what is there, for one command's
  :class:`RunLayout` (:data:`TRAIN_LAYOUT`, :data:`FINETUNE_LAYOUT`): it refuses a directory
  holding another command's run, a fresh run over a run that holds results, a resume with
  nothing to resume, and a directory that cannot be written. A directory holding only a
  command's config and log (a run killed before its first checkpoint) starts fresh.
* **Logs**: :func:`truncate_log` cuts a JSON-lines ``log.jsonl`` back to the step a resumed run
  continues from.
* **Hashes**: :func:`file_sha256`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from envs.files import atomic_path, atomic_save_safetensors, atomic_write_bytes, atomic_write_text

__all__ = [
    "FINETUNE_LAYOUT",
    "LAYOUTS",
    "TRAIN_LAYOUT",
    "RunDirError",
    "RunLayout",
    "atomic_path",
    "atomic_save_safetensors",
    "atomic_write_bytes",
    "atomic_write_text",
    "file_sha256",
    "prepare_run_dir",
    "remove_stale_temps",
    "truncate_log",
    "unwritable_reason",
]


class RunDirError(ValueError):
    """A run directory that cannot be used as asked (the message names the directory)."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def remove_stale_temps(directory: str | Path) -> list[Path]:
    """Delete the ``.NAME.tmpPID`` files in ``directory`` whose process is gone (left by a
    ``SIGKILL`` between writing and renaming); returns the removed paths."""
    removed: list[Path] = []
    directory = Path(directory)
    if not directory.is_dir():
        return removed
    for tmp in directory.glob(".*.tmp*"):
        pid_text = tmp.name.rsplit(".tmp", 1)[1]
        if not pid_text.isdigit() or int(pid_text) == os.getpid() or _pid_alive(int(pid_text)):
            continue
        tmp.unlink(missing_ok=True)
        removed.append(tmp)
    return removed


def unwritable_reason(directory: str | Path) -> str | None:
    """Why ``directory`` cannot be created or written (a probe file is written and removed), or
    ``None`` when it can: callers turn the reason into their own one-line error."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write-test.tmp{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        return str(exc.strerror or exc)
    return None


# --------------------------------------------------------------------------- hashes and logs


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, hex (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def truncate_log(path: str | Path, step: int) -> int:
    """Rewrite the JSON-lines log at ``path`` without the records a killed attempt wrote after
    the checkpoint at ``step`` (records with a larger step, ``"data"`` records of that step, and
    a torn last line); atomic. Returns the number of records dropped."""
    path = Path(path)
    if not path.is_file():
        return 0
    kept, dropped = [], 0
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
            rstep = int(record["step"])
        except (ValueError, KeyError, TypeError):
            dropped += 1
            continue
        if rstep > step or (rstep == step and record.get("kind") == "data" and step > 0):
            dropped += 1
            continue
        kept.append(line)
    if dropped:
        atomic_write_text(path, "".join(f"{line}\n" for line in kept))
    return dropped


# --------------------------------------------------------------------------- run directories


@dataclass(frozen=True)
class RunLayout:
    """What one command keeps in its run directory.

    ``config``: the file the run's config is saved to (rewritten by every start, never removed
    here); ``results``: the files that hold progress or results (a resume state, a checkpoint,
    the result); ``resume_from``: the one a resume continues from; ``fresh_blocks``: the files
    that refuse a fresh start (without ``overwrite``); ``files``: every file or directory the
    command writes (removed when a run is replaced)."""

    command: str
    config: str
    results: tuple[str, ...]
    resume_from: str
    fresh_blocks: tuple[str, ...]
    files: tuple[str, ...]
    #: whether the command offers ``--overwrite`` (named in the refusal)
    can_overwrite: bool = False


TRAIN_LAYOUT = RunLayout(
    command="train",
    config="config.yaml",
    results=("last.pt", "best.pt"),
    resume_from="last.pt",
    # `train --resume --out DIR` reads DIR's config.yaml: a fresh run must not replace it
    fresh_blocks=("config.yaml", "last.pt", "best.pt"),
    files=("config.yaml", "last.pt", "best.pt", "log.jsonl", "tb"),
)
FINETUNE_LAYOUT = RunLayout(
    command="finetune",
    config="config.json",
    results=("state.safetensors", "tracker.safetensors", "residual.safetensors"),
    resume_from="state.safetensors",
    # a config and log without results (killed in the first rollout) lose nothing
    fresh_blocks=("state.safetensors", "tracker.safetensors", "residual.safetensors"),
    files=(
        "config.json",
        "state.safetensors",
        "tracker.safetensors",
        "residual.safetensors",
        "log.jsonl",
        "snapshots",
        "val.json",
        "sb3",
    ),
    can_overwrite=True,
)
#: every command's layout: a directory holding another command's files is refused
LAYOUTS = (TRAIN_LAYOUT, FINETUNE_LAYOUT)


def _present(out: Path, names: tuple[str, ...]) -> list[str]:
    return [name for name in names if (out / name).exists()]


def _other_commands_run(out: Path, layout: RunLayout) -> str | None:
    mine = set(layout.files)
    for other in LAYOUTS:
        if other.command == layout.command:
            continue
        held = [n for n in _present(out, (other.config, *other.results)) if n not in mine]
        if held:
            return f"a `pointtrack {other.command}` run ({', '.join(held)})"
    return None


def _remove(out: Path, names: list[str]) -> None:
    for name in names:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)


def prepare_run_dir(
    out: str | Path, layout: RunLayout, *, resume: bool, overwrite: bool = False
) -> Path | None:
    """Decide what a run into ``out`` does, before any data is built: returns the file to
    resume from (``layout.resume_from``), or ``None`` for a start from the beginning.

    * A directory holding another command's run (its config or results) is refused, whatever
      the flags: replacing it would mix or delete that run's files.
    * ``resume``: continues from ``layout.resume_from``; a directory holding this command's
      config but no results (a run killed before its first checkpoint) starts from the
      beginning; one holding neither is refused (a typo would otherwise start a new run where an
      old one was meant), and so is one holding results but no resume state.
    * Without ``resume``: a directory holding any of ``layout.fresh_blocks`` is refused unless
      ``overwrite``.
    * Starting from the beginning removes the files of ``layout.files`` a previous run left
      (but the config, which the run rewrites), so the call is idempotent.
    * An ``out`` that cannot be written is refused.

    Raises :class:`RunDirError` (``resume`` with ``overwrite`` too)."""
    out = Path(out)
    if resume and overwrite:
        raise RunDirError("--resume and --overwrite exclude each other")
    if out.exists() and not out.is_dir():
        raise RunDirError(f"--out {out} exists and is not a directory")
    other = _other_commands_run(out, layout) if out.is_dir() else None
    if other is not None:
        raise RunDirError(
            f"--out {out} holds {other}, not a `pointtrack {layout.command}` run: "
            f"choose another --out"
        )
    held = _present(out, layout.files)
    results = _present(out, layout.results)
    if resume:
        if (out / layout.resume_from).is_file():
            return out / layout.resume_from
        if results:
            raise RunDirError(
                f"nothing to resume in {out}: it holds {', '.join(results)} but no "
                f"{layout.resume_from} (choose another --out)"
            )
        if not (out / layout.config).exists():
            raise RunDirError(
                f"nothing to resume in {out}: it holds no {layout.resume_from} and no "
                f"{layout.config} (check --out, or drop --resume to start a run)"
            )
    else:
        blocking = _present(out, layout.fresh_blocks)
        if blocking and not overwrite:
            replace = " or --overwrite to replace it" if layout.can_overwrite else ""
            raise RunDirError(
                f"--out {out} already holds a run ({', '.join(held)}): pass --resume to "
                f"continue it{replace}, or choose another --out"
            )
    _remove(out, [name for name in held if name != layout.config])
    why = unwritable_reason(out)
    if why is not None:
        raise RunDirError(f"cannot write to the run directory {out}: {why}")
    return None
