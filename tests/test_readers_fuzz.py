"""A small fuzz run of the recording readers (tests/helpers/fuzz_readers.py; the full one is
``benchmarks/robustness/fuzz_readers.py --n 2000``).

Mutated files of every format are read in forked children; no read may crash, hang, raise an unclear error or
return events that break the readers' invariants.
"""

import numpy as np

from eventcap.io import read_recording
from helpers import fuzz_readers


def test_fuzz_small_run_has_no_crash_hang_or_silent_error():
    res = fuzz_readers.run_fuzz(n=120, seed=7, workers=2, timeout_s=30.0)
    counts = res["counts"]
    assert sum(counts.values()) == 120
    for outcome in fuzz_readers.MUST_BE_ZERO:
        assert counts[outcome] == 0, (outcome, res["examples"].get(outcome))
    # The mutations do bite: most are refused with a clear error, some are repaired.
    assert counts["rejected"] >= 60 and counts["repaired"] >= 5
    assert set(res["by_format"]) == {e for e in ("aedat4", "evt2", "evt3", "dat", "hdf5", "npz", "npy", "npy_4n",
                                                 "csv", "aedat2", "aedat2_aps", "aedat3", "rpg", "aedat4_real")
                                     if e != "aedat4_real" or fuzz_readers.REAL_AEDAT4.is_file()}


def test_corpus_reads_back_exactly(tmp_path):
    corpus = fuzz_readers.make_corpus(tmp_path, include_real=False)
    ref = fuzz_readers.synthetic_recording()
    for entry in corpus:
        r = read_recording(entry.path, **({"width": 64, "height": 48} if entry.name.startswith("npy") else {}))
        assert fuzz_readers.invariant_violations(r) == [], entry.name
        np.testing.assert_array_equal(r.events, ref.events if entry.name != "aedat3" else ref.events[
            np.arange(len(ref.events)) % 11 != 10], err_msg=entry.name)  # aedat3: every 11th event marked invalid
        # AEDAT 2.0 stores jAER's 32-bit µs counter
        assert r.t_offset_us == ref.t_offset_us % (2**32 if entry.name.startswith("aedat2") else 2**62), entry.name
        if entry.name == "aedat3":
            np.testing.assert_array_equal(r.frames.images, ref.frames.images)
            np.testing.assert_array_equal(r.frames.t_us, ref.frames.t_us)


def test_mutations_are_deterministic():
    import random

    data = bytes(range(256)) * 4
    for kind in fuzz_readers.KINDS:
        a = fuzz_readers.mutate(data, kind, random.Random(3))
        b = fuzz_readers.mutate(data, kind, random.Random(3))
        assert a == b and a != data, kind
