"""Options that several subcommands share."""

from __future__ import annotations

__all__ = ["add_light_args"]


def add_light_args(p) -> None:
    """The options every frame-reading subcommand shares: where lights come from, ambient."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--lights", help="lights.txt: optional count line, then 'x y z' per frame")
    g.add_argument("--yale-names", action="store_true",
                   help="parse lights from Yale B names (..._P00A+035E+15.pgm)")
    p.add_argument("--ambient", help="ambient-only control frame to subtract")
