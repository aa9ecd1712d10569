"""``streamcal`` command line: thin — parse, call the library, print (docs/cli.md).

Each command lives in its own module of this package and provides ``register(subparsers)``,
which adds its parser and sets ``func`` to a callable ``(args) -> int`` (the exit code).
Exit codes: 0 success; 1 the data cannot support the request; 2 usage or input error, or an
output that cannot be written (one line naming it); 141 (128 + SIGPIPE, as a shell tool killed
by it) when standard output is a pipe closed early (``streamcal fit … | head -3``), quietly.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from ..errors import StreamcalError

#: Order in ``--help``; modules found in this package but not listed come after.
ORDER = ("demo", "fit", "diagnose", "report", "convert", "export", "check", "apply", "batch", "replay",
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
        code = int(args.func(args) or 0)
        sys.stdout.flush()           # a closed pipe is found here, not at the interpreter's exit
        return code
    except BrokenPipeError:
        # the reader is gone: what is still buffered goes nowhere, and no traceback
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):   # no file behind sys.stdout (captured)
            pass
        return 141
    except StreamcalError as exc:
        print(f"streamcal {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:           # an output or device refused (streamcal.atomic names it)
        print(f"streamcal {args.command}: error: {os_error_text(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def os_error_text(exc: OSError) -> str:
    """``PATH: what is wrong`` for an OSError (its ``str`` when it names no file)."""
    if exc.filename is None:
        return str(exc)
    return f"{exc.filename}: {exc.strerror or exc}"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
