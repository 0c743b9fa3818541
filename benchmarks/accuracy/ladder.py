"""The oracle ladder's table: every rung and method of the ladder presets, side by side for each set of captures
(10 and 25 fps, tuning and check seeds), from the benchmarks' own results (`benchmark.json`).

    python benchmarks/accuracy/ladder.py [--run] [--sets ladder ladder25 ladder_check ladder25_check]
                                         [--root runs/benchmark] [--markdown] [-- OVERRIDES...]

--run first runs `eventcap benchmark benchmark=<set>` for each set (a resumed run recomputes nothing committed;
OVERRIDES go to each, e.g. `only=["a default","a frames_smooth"]` or `cache_dir=...`); without it the sets' existing
results are read. The rungs (conf/benchmark/ladder.yaml): (a) the truth at the intensity frames, (b) (a) with each event
term alone and all off, (c) the truth every 10 ms, (d) the simulated detector's default noise, (e) BlazePose.
Columns: AE (mm, Procrustes), depth (root-relative error along the line of sight, mm), MPJVE (mm/s), the fast-peak
error (median |relative error| of the end effectors' peak speed per inter-frame interval where the truth peaks at
3 m/s or more, pooled over the set's captures; the pairs' count), and the signed peak-speed error by true-speed bin
(negative: too slow). Also each set's time per 40 ms of the solve. Check seeds are for reporting only.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SETS = ("ladder", "ladder25", "ladder_check", "ladder25_check")
LABELS = {"ladder": "10 fps, tuning", "ladder25": "25 fps, tuning", "ladder_check": "10 fps, check",
          "ladder25_check": "25 fps, check"}


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def _num(v, d: int = 1) -> str:
    return "-" if v is None else f"{v:.{d}f}"


def rows_of(result: dict) -> list[dict]:
    """The table rows of a benchmark's results, each with the fields the ladder prints."""
    out = []
    for r in result["table"]:
        bins = r.get("peak_speed_signed_by_bin") or {}
        solve = (r.get("s_per_batch") or {}).get("solve")
        out.append({"row": r["method"], "AE": r.get("AE_mm"), "depth": r.get("depth_mm"), "MPJVE": r.get("MPJVE_mm_s"),
                    "fast": r.get("peak_speed_err_fast"), "pairs": r.get("n_fast_pairs") or 0,
                    "bins": {k: v.get("median") for k, v in bins.items()}, "runs": f"{r['evaluated']}/{r['runs']}",
                    "solve_s": solve})
    return out


def table(name: str, rows: list[dict], markdown: bool) -> str:
    head = ["row", "AE mm", "depth mm", "MPJVE mm/s", "fast peak", "pairs", "0.5-1.5", "1.5-3", "3-6", "6+", "runs"]
    body = [[r["row"], _num(r["AE"]), _num(r["depth"]), _num(r["MPJVE"], 0), _pct(r["fast"]), str(r["pairs"]),
             *(_pct(r["bins"].get(k)) for k in ("0.5-1.5", "1.5-3", "3-6", "6+")), r["runs"]] for r in rows]
    title = f"{LABELS.get(name, name)} ({name})"
    if markdown:
        lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(b) + " |" for b in body]
        return "\n".join(lines)
    widths = [max(len(str(c)) for c in col) for col in zip(head, *body)]
    fmt = lambda cells: "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w)  # noqa: E731
                                  for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([title, fmt(head), "  ".join("-" * w for w in widths), *(fmt(b) for b in body)])


def main() -> None:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="+", default=list(SETS))
    ap.add_argument("--root", type=Path, default=ROOT / "runs" / "benchmark")
    ap.add_argument("--run", action="store_true", help="run the sets' benchmarks first")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    for name in args.sets:
        if args.run:
            subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "benchmark", f"benchmark={name}", *extra],
                           check=False)
        path = args.root / name / "benchmark.json"
        if not path.is_file():
            print(f"{name}: no results ({path}); run it with --run")
            continue
        print(table(name, rows_of(json.loads(path.read_text())), args.markdown))
        print()


if __name__ == "__main__":
    main()
