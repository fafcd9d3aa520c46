"""The ``prognos`` command line.

prognos study --list
prognos study NAME [--runs N] [--quick] [--out DIR] [--device cpu|cuda] [--seed S]
prognos study all [--quick] ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main", "build_parser"]


def _add_study(sub) -> None:
    p = sub.add_parser(
        "study",
        help="reproduce a paper's experiment and write table.md, results.csv, run.json, figures",
        description="Run a study (one per paper) and write its table and figures.",
        epilog="examples:\n  prognos study --list\n  prognos study elm-stsckf --quick\n"
        "  prognos study anfis-training --runs 50 --out results",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", nargs="?", help="study name, or 'all'")
    p.add_argument("--list", action="store_true", help="list the studies and exit")
    p.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: the paper's)")
    p.add_argument("--quick", action="store_true", help="reduced protocol (smoke test)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output folder")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--seed", type=int, default=0, help="base seed")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_study)


def _cmd_study(args) -> int:
    from .studies import StudyConfig, discover_studies, run_study

    try:
        studies = discover_studies()
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.list or args.name is None:
        for name, st in studies.items():
            print(f"{name:20s} paper {st.paper:8s} {st.title}")
        return 0 if args.list else 2
    try:
        cfg = StudyConfig(
            runs=args.runs,
            quick=args.quick,
            out=args.out,
            device=args.device,
            seed=args.seed,
            progress=not args.no_progress,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    names = list(studies) if args.name == "all" else [args.name]
    unknown = [n for n in names if n not in studies]
    if unknown:
        print(
            f"error: unknown study {unknown[0]!r}; valid: {', '.join(studies)} or all",
            file=sys.stderr,
        )
        return 2
    for n in names:
        _, text = run_study(studies[n], cfg)
        print(text)
        print(f"[written to {Path(args.out) / n}]")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="prognos", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="command")
    _add_study(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if not getattr(args, "func", None):
        ap.print_help()
        return 2
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
