"""``streamcal`` command line: thin — parse, call the library, print (docs/cli.md).

Each command lives in its own module of this package and provides ``register(subparsers)``,
which adds its parser and sets ``func`` to a callable ``(args) -> int`` (the exit code).
Exit codes: 0 success; 1 the data cannot support the request; 2 usage or input error.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from ..errors import StreamcalError

#: Order in ``--help``; modules found in this package but not listed come after.
ORDER = ("demo", "fit", "diagnose", "report", "convert", "export", "apply", "batch", "replay",
         "daemon", "serial", "record")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="streamcal",
        description="Robust streaming calibration of MPU-9250 magnetometers and accelerometers, "
                    "with diagnosis of what the sensor model misses.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    found = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")]
    for name in sorted(found, key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n)):
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except StreamcalError as exc:
        print(f"streamcal {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
