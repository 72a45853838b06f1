"""Confusion table of the diagnosis over seeded synthetic drives (every catalogue effect under
several world laws, null cases with soil varying along the path, an out-of-catalogue effect).

    python scripts/diagnosis_study.py --out out/diagnosis_study

Appends one JSON line per case to DIR/cases.jsonl (a rerun skips the cases already there) and
writes DIR/confusion.md. Each case: the scenario's truth is used only to score the verdict.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "diagnosis"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/diagnosis_study", help="output directory")
    ap.add_argument("--quick", action="store_true", help="one case per kind")
    args = ap.parse_args(argv)

    from scenarios import STUDY_CASES

    from torchsoil.diagnosis.study import run_study

    cases = STUDY_CASES[::3] if args.quick else STUDY_CASES
    table = run_study(cases, Path(args.out))
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
