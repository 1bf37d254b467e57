"""The `jaxps` command: one parser, a subcommand per module of this package."""

from __future__ import annotations

import argparse
import importlib.metadata
import sys

from . import _demo, _reconstruct, _relight, _report

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxps", description="Photometric-stereo face capture and reflectance modelling."
    )
    version = importlib.metadata.version("jaxps")
    parser.add_argument("--version", action="version", version=f"jaxps {version}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in (_reconstruct, _demo, _report, _relight):
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxps {args.command}: error: {err}", file=sys.stderr)
        return 2
