"""Command line of segs.report (see the package doc)."""
from __future__ import annotations

import argparse
import sys

from segs.config import user_errors_exit
from segs.report import __doc__ as _DOC
from segs.report.write import write_report


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m segs.report", description=_DOC,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("dirs", nargs="+", metavar="DIR", help="run or multirun folders (searched recursively)")
    p.add_argument("--out", default=None, help="output folder (default: DIR, or the common parent of several)")
    p.add_argument("--min-tracked", type=float, default=0.9, help="stability: a level fails below this tracked fraction")
    p.add_argument("--max-ate-cm", type=float, default=5.0, help="stability: a level fails above this ATE RMSE (cm)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with user_errors_exit():
        written = write_report(args.dirs, args.out, min_tracked=args.min_tracked, max_ate_m=args.max_ate_cm / 100)
    for path in written.values():
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
