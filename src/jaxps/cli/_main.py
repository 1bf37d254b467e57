"""The `jaxps` command: one parser, a subcommand per module of this package."""

from __future__ import annotations

import argparse
import gc
import importlib
import importlib.metadata
import os
import sys

from . import _args
from ._cache import enable_compilation_cache

__all__ = ["build_parser", "console", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxps", description="Photometric-stereo face capture and reflectance modelling."
    )
    version = importlib.metadata.version("jaxps")
    parser.add_argument("--version", action="version", version=f"jaxps {version}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_args.reconstruct_parser, _args.calibrate_parser, _args.demo_parser,
                _args.report_parser, _args.relight_parser):
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the `jaxps` command on `argv` (default `sys.argv[1:]`); returns its exit code."""
    return _run(argv, freeze=False)


def console() -> int:
    """The installed `jaxps` script and `python -m jaxps`: `main()` for a process that ends
    with the command (the caller exits with the returned code).

    A command's process ends with it, so Python's cyclic garbage collector is told to leave
    alone every object that exists once the command's modules are imported, and again at the
    end (`gc.freeze`). Without that, the collections during the run and at exit walk the
    objects of JAX's modules again and again: `benchmarks/bench_cli.py` times a warm
    `jaxps reconstruct` of five 1 MP frames both ways (`gc_freeze` in `cli.json`). Objects are
    still freed by reference counting; only cycles among frozen ones are left for the
    process's end.
    """
    return _run(None, freeze=True)


def _log_above_bars():
    from ..report._progress import log_above_bars  # the commands' bars write the warnings

    log_above_bars(always=True)


def _run(argv, freeze):
    parser = build_parser()
    args = parser.parse_args(argv)
    out = getattr(args, "out", None)
    if args.command != "report" and out and os.path.exists(out) and not os.path.isdir(out):
        # before the work: writing the outputs would fail only at the end
        print(f"jaxps {args.command}: error: --out {out} is a file; the outputs need a folder",
              file=sys.stderr)
        return 2
    enable_compilation_cache()
    _log_above_bars()
    try:
        command = importlib.import_module(f"{__package__}.{args.module}")
        if freeze:
            gc.freeze()
        return command.run(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxps {args.command}: error: {err}", file=sys.stderr)
        return 2
    finally:
        if freeze:
            gc.freeze()
