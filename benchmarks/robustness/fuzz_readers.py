"""Fuzz the recording readers: mutate small valid files of every format and read each in its own process.

Usage: ``python3 benchmarks/robustness/fuzz_readers.py --n 2000 [--seed 0] [--workers 2] [--timeout 20]``

The corpus, the mutations and the outcomes (loaded, repaired, changed_undetected, rejected; unclear_error,
silently_wrong, crashed and hung must be 0) are described in tests/helpers/fuzz_readers.py, which
tests/test_readers_fuzz.py runs small.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the fuzzer: tests/helpers

from tests.helpers.fuzz_readers import MUST_BE_ZERO, OUTCOMES, run_fuzz


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="number of mutated files to read")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2, help="children reading at the same time")
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds before a read counts as hung")
    ap.add_argument("--no-real", action="store_true", help="leave the real AEDAT4 file out of the corpus")
    ap.add_argument("--only", help="fuzz only corpus entries whose name contains this (e.g. aedat4, rpg)")
    args = ap.parse_args(argv)
    logging.getLogger("eventcap.io").setLevel(logging.ERROR)  # the corpus' own repair notes are expected
    res = run_fuzz(args.n, args.seed, args.workers, args.timeout, not args.no_real, args.only,
                   log=lambda s: print(s, file=sys.stderr, flush=True))
    c = res["counts"]
    print(f"{args.n} mutated files, seed {args.seed}, {res['seconds']:.1f} s "
          f"({1000 * res['seconds'] / max(args.n, 1):.1f} ms per read, {args.workers} workers)")
    for k in OUTCOMES:
        print(f"  {k:<20} {c.get(k, 0):>6}")
    print("by format:")
    for name, cc in sorted(res["by_format"].items()):
        print(f"  {name:<12} " + "  ".join(f"{k}={cc[k]}" for k in OUTCOMES if cc.get(k)))
    for k in ("repaired", "changed_undetected", "rejected", *MUST_BE_ZERO):
        for ex in res["examples"].get(k, [])[:3]:
            print(f"  e.g. {k}: {ex}")
    return 1 if any(c.get(k, 0) for k in MUST_BE_ZERO) else 0


if __name__ == "__main__":
    sys.exit(main())
