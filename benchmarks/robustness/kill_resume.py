"""Kill a multi-batch run with SIGKILL at random moments, resume it, and check the result: a run killed at any
moment and started again must end with the outputs of an uninterrupted run (eventcap/core/cache.py: atomic commits).

For each trial: start `eventcap run` on the toy pipeline (tests/toy_stages.py) in a fresh cache, SIGKILL its whole
process group (``--kill group``) or the driver alone (``--kill driver``: its pool / Dask workers must then die on their
own) at a random time, note which entries were committed, run the same command again, and check that (1) the final
metrics and every cache entry's files equal an uninterrupted run, (2) the resumed run computed none of the entries
committed before the kill, and (3) with ``--kill driver``, no process of the killed run is left 10 s after the kill.

    python benchmarks/robustness/kill_resume.py --trials 20 [--executor serial|processes|dask|mixed|all] [--kill driver]

The harness is tests/helpers/kill_resume.py (tests/test_kill_resume.py runs it small).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the harness: tests/helpers

from tests.helpers.kill_resume import main

if __name__ == "__main__":
    sys.exit(main())
