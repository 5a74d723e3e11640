"""`pointtrack generate`."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""


def run(args: argparse.Namespace) -> int:
    raise SystemExit("pointtrack generate: not implemented yet")
