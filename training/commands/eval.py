"""`pointtrack eval`."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""


def run(args: argparse.Namespace) -> int:
    raise SystemExit("pointtrack eval: not implemented yet")
