"""Fuzz the recording readers: damage small valid files of every format and read each in its own process.

    python benchmarks/robustness/fuzz_readers.py --n 2000 --seed 0      # the table, counts per class and format

The corpus, the damage and the outcomes are described in tests/helpers/fuzz_readers.py, which
tests/test_readers_fuzz.py runs small.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tests.helpers.fuzz_readers import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
