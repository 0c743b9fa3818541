"""Where the tests and their data are."""

from __future__ import annotations

from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
ROOT = TESTS.parent
#: The real DAVIS346 recording (MIT, 1.2 MB) shipped with the tests; origin and licence in tests/data/real/SOURCE.md.
REAL_DAVIS346 = TESTS / "data" / "real" / "davis346_lab_aps.aedat4"
