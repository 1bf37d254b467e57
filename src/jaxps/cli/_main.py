"""The `jaxps` command: one parser, a subcommand per module of this package."""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import sys

from . import _args
from ._cache import enable_compilation_cache

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxps", description="Photometric-stereo face capture and reflectance modelling."
    )
    version = importlib.metadata.version("jaxps")
    parser.add_argument("--version", action="version", version=f"jaxps {version}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_args.reconstruct_parser, _args.demo_parser, _args.report_parser,
                _args.relight_parser):
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    enable_compilation_cache()
    try:
        return importlib.import_module(f"{__package__}.{args.module}").run(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxps {args.command}: error: {err}", file=sys.stderr)
        return 2
