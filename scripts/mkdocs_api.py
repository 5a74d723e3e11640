"""mkdocs hook: the API reference pages, one per package, generated at build time.

``docs/api/PACKAGE.md`` is made from every public module of ``envs``, ``trackers`` and
``training`` (found by walking the source tree, so a new or moved module needs no edit here):
one ``::: module`` block each, rendered by mkdocstrings from the docstrings. Nothing is imported.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {
    "envs": "The world the agent lives in: data, geometry, metrics, weather, the Gymnasium env.",
    "trackers": "The torch trackers (P2B, BAT, GPT, M2-Track) and the non-learned baselines.",
    "training": "Pretraining, RL fine-tuning, evaluation, selection, rendering and the CLI.",
}
# the command modules are documented by `pointtrack COMMAND --help`
SKIPPED = ("training.commands",)


def public_modules(package: str) -> list[str]:
    """Dotted names of the modules of ``package`` (a folder under the repository root) whose
    path has no part starting with ``_`` (``__init__`` gives the package itself), sorted."""
    names = []
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        if any(p.startswith("_") for p in parts):
            continue
        name = ".".join(parts)
        if not name.startswith(SKIPPED):
            names.append(name)
    return names


def page(package: str) -> str:
    """The Markdown of ``api/PACKAGE.md``."""
    blocks = [f"# `{package}`\n\n{PACKAGES[package]}\n"]
    for name in public_modules(package):
        blocks.append(f"::: {name}\n    options:\n      heading_level: 2\n")
    return "\n".join(blocks)


def on_files(files: Files, config) -> Files:
    for package in PACKAGES:
        files.append(File.generated(config, f"api/{package}.md", content=page(package)))
    return files
