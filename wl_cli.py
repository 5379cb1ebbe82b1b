"""``wl``: the command line of wheel-loader-gym (the top floor: it imports every package, none imports it).

Each subcommand is a small function over the packages; errors a user can fix come out as one line
``wl: error: ...`` with exit code 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

SUBCOMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}


def _params_cmd(args: argparse.Namespace) -> int:
    from wl_env.params import PROVENANCE, LoaderParams

    p = LoaderParams.from_dict(json.loads(args.set)) if args.set else LoaderParams()
    if args.json:
        print(json.dumps(p.to_dict(), indent=1))
        return 0
    for name, value in p.to_dict().items():
        unit, source = PROVENANCE.get(name, ("", ""))
        print(f"{name:15s} {str(value):45s} {unit:30s} {source}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="wl",
        description="wheel-loader-gym: the wheel loader short loading cycle as a Gymnasium environment, "
        "its optimal control benchmark, and controllers scored against it.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("params", help="print the model parameters with units and provenance")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.add_argument("--set", metavar="JSON", help='overrides, e.g. \'{"M_load": 12000}\' (validated)')
    p.set_defaults(func=_params_cmd)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        import wl_env

        print(wl_env.__version__)
        return 0
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, RuntimeError, json.JSONDecodeError) as exc:
        print(f"wl: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("wl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
