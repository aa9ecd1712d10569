"""``streamcal batch fit|diagnose FILES… [--jobs N] -o SUMMARY.csv`` (docs/cli.md)."""
from __future__ import annotations

import sys

from ._common import add_skip_bad_rows, compass_choice, say_skipped
from ._output import check_output, messages_to


def register(sub) -> None:
    p = sub.add_parser("batch", help="fit or diagnose many recordings, one summary row each",
                       description="Run fit or diagnose over many recordings in parallel and "
                                   "write one CSV row per file (a failing file is a row with its "
                                   "error, not the end of the run).")
    p.add_argument("task", choices=("fit", "diagnose"))
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="recordings: tracks, autopilot logs (.bin, .ulg), captures (the formats "
                        "the other commands read)")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="worker processes (default: the number of CPUs)")
    p.add_argument("-o", "--output", required=True, metavar="SUMMARY.csv",
                   help="summary CSV (written atomically; - for stdout)")
    p.add_argument("--compass", type=compass_choice, default=None, metavar="N",
                   help="autopilot logs: compass instance from 0 (default: the one the autopilot "
                        "uses first)")
    add_skip_bad_rows(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """Exit 0 when every file succeeded, 1 when some failed (the summary is written either way)."""
    from tqdm import tqdm

    from ..batching import batch, write_summary
    from ..errors import InputError

    if args.compass == "all":
        raise InputError("--compass all: batch reads one compass per log; give its instance "
                         "number")
    if args.jobs is not None and args.jobs < 1:
        raise InputError(f"--jobs: expected a positive number of workers, got {args.jobs}")
    check_output(args.output)
    with tqdm(total=len(args.files), file=sys.stderr, unit="file", desc=args.task) as bar:
        rows = batch(args.files, args.task, jobs=args.jobs, progress=lambda row: bar.update(1),
                     skip_bad_rows=args.skip_bad_rows, compass=args.compass)
    for r in rows:
        say_skipped(r["path"], r.get("skipped_rows") or 0,
                    [r["first_skipped"]] if r.get("first_skipped") else [], "streamcal batch")
    write_summary(args.output, rows)
    failed = [r for r in rows if r["status"] != "ok"]
    for r in failed:
        print(f"streamcal batch: {r['path']}: {r['error']}", file=sys.stderr)
    print(f"{len(rows) - len(failed)} of {len(rows)} files ok; summary written: {args.output}",
          file=messages_to(args.output))
    return 1 if failed else 0
