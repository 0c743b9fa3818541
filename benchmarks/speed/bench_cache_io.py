"""What the cache's I/O costs per commit, per group and per array: a finished run's outputs committed again.

    python benchmarks/speed/bench_cache_io.py RUN_DIR [--repeat 3]

Reads every output a finished run committed (``eventcap.core.runner.load_finished_run``: the node's ports, per batch
for per-batch nodes), then commits them again, entry by entry as the runner does (``Cache.commit``: the zarr groups
and arrays, the manifest with every file's digest, the atomic rename), into a fresh cache in a temporary folder, and
loads each back (``Cache.load``). Prints CPU seconds (``time.process_time``) for the writes and the reads, per run of
all entries and per zarr group and array written, for each repeat. Issue 55 (cache I/O ~0.29 s per 40 ms of a 1 s
run: hundreds of small arrays). Nothing is asserted; the figures are for comparing code on the same machine.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def outputs_of(run_dir: Path) -> list[tuple[str, dict]]:
    """[(stage, {port: artifact})] of every entry the run committed, in the pipeline's order."""
    from eventcap.core.runner import load_finished_run

    runner, res = load_finished_run(run_dir)
    entries: dict[tuple[str, object], tuple[str, dict]] = {}
    for node in runner.by_name.values():
        for port in node.spec.outputs:
            for batch, art in runner.load_output(res, f"{node.name}.{port}").items():
                entries.setdefault((node.name, batch), (node.spec.name, {}))[1][port] = art
    return list(entries.values())


def count(folder: Path) -> tuple[int, int]:
    """(zarr groups, zarr arrays) under a folder."""
    import json

    groups = arrays = 0
    for meta in folder.rglob("zarr.json"):
        kind = json.loads(meta.read_text()).get("node_type")
        groups += kind == "group"
        arrays += kind == "array"
    return groups, arrays


def main(argv=None) -> int:
    from eventcap.core.cache import Cache

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    entries = outputs_of(Path(args.run_dir))
    print(f"{args.run_dir}: {len(entries)} entries")
    for rep in range(args.repeat):
        tmp = Path(tempfile.mkdtemp(prefix="bench_cache_io_"))
        try:
            cache = Cache(tmp / "cache")
            t0 = time.process_time()
            made = [cache.commit(stage, f"bench{rep}x{i:04d}", {"bench": i}, outs)
                    for i, (stage, outs) in enumerate(entries)]
            t_write = time.process_time() - t0
            t0 = time.process_time()
            for entry, (_, outs) in zip(made, entries):
                for port, art in outs.items():
                    cache.load(entry, port, type(art))
            t_read = time.process_time() - t0
            groups, arrays = count(tmp / "cache")
            print(f"repeat {rep + 1}: write {t_write:.2f} CPU s ({1000 * t_write / len(entries):.1f} ms per entry; "
                  f"{groups} groups, {arrays} arrays: {1000 * t_write / max(arrays, 1):.1f} ms per array all told), "
                  f"read {t_read:.2f} CPU s ({1000 * t_read / max(arrays, 1):.1f} ms per array)")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
