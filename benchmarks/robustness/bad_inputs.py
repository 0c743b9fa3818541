"""The cases of issue 48 ("Bad input: never silently wrong, never stuck"), run for real through the command line.

    python benchmarks/robustness/bad_inputs.py       # the issue's table, every case run for real (about 4 min)

The cases are built in tests/helpers/bad_inputs.py, which tests/test_bad_input.py runs too.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tests.helpers.bad_inputs import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
