"""Where a command's messages go when it writes an output (the rule itself is
:mod:`streamcal.atomic`'s: parents created, ``-`` is standard output, streams written directly,
a directory or an unwritable place refused with one line)."""
from __future__ import annotations

import sys

from ..atomic import is_stdout, prepare_output


def check_output(output) -> None:
    """Say now, before the work, when ``output`` (a file, ``-`` or None) cannot be written: a
    directory, a place that cannot be written (:func:`streamcal.atomic.prepare_output`, which
    also creates its missing parent directories)."""
    if output is not None:
        prepare_output(output)


def messages_to(output):
    """The stream for a command's human messages: standard error when ``output`` is standard
    output (``-o -``, ``-o /dev/stdout``), so that stdout carries the output alone; else
    standard output."""
    return sys.stderr if output is not None and is_stdout(output) else sys.stdout
