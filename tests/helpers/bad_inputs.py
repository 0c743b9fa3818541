"""The cases of issue 48 ("Bad input: never silently wrong, never stuck"), run for real through the command line.

Each case builds a damaged input from a small simulated recording (not real sensor data), runs ``eventcap preview``,
``eventcap convert`` or ``eventcap run`` on it in a child process (a time limit, the child's peak memory from
``wait4``) and reports the exit code and the line that says what happened. ``fuzz_readers.py`` prints the table;
``python3 benchmarks/robustness/bad_inputs.py`` prints it alone.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from eventcap.events import EVENT_DTYPE  # noqa: E402

W, H = 240, 180  # a DAVIS240C
CLI = [sys.executable, "-m", "eventcap.apps.cli"]


@dataclass
class Outcome:
    code: int | None  # None: killed at the time limit
    seconds: float
    peak_mb: float
    out: str
    left: list[str]  # what a refused run left on disk (eventcap run cases)

    def line(self) -> str:
        """The line that says what happened: the error, the repairs, or the summary."""
        lines = [s.strip() for s in self.out.splitlines() if s.strip()]
        if self.code is None:
            return f"HANG: killed after {self.seconds:.0f} s"
        if "Traceback" in self.out:
            return "TRACEBACK: " + (lines[-1] if lines else "")
        pick = [s for s in lines if s.startswith(("eventcap preview:", "eventcap convert:", "eventcap run:",
                                                  "repaired:", "- node"))]
        pick += [s for s in lines if s.startswith(("wrote", "read "))] if self.code == 0 else []
        return " | ".join(pick[:3]) if pick else (lines[-1] if lines else "")


def run(argv: list[str], cwd: Path, timeout_s: float = 60.0, env: dict | None = None) -> Outcome:
    """Run the CLI in a child process (its own session, so a stuck child is killed with its children), with the
    child's peak resident memory."""
    t0 = time.perf_counter()
    env = {**os.environ, "EVENTCAP_CACHE_DIR": str(cwd / "cache"), "PYTHONPATH": str(ROOT)} if env is None else env
    with tempfile.TemporaryFile() as log:
        p = subprocess.Popen([*CLI, *argv], cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, start_new_session=True)
        code, usage = None, None
        while True:
            pid, status, usage = os.wait4(p.pid, os.WNOHANG)
            if pid:
                code = os.waitstatus_to_exitcode(status)
                break
            if time.perf_counter() - t0 > timeout_s:
                os.killpg(p.pid, signal.SIGKILL)
                _, _, usage = os.wait4(p.pid, 0)
                break
            time.sleep(0.05)
        p.returncode = code if code is not None else -9
        log.seek(0)
        out = log.read().decode("utf-8", "replace")
    return Outcome(code, time.perf_counter() - t0, usage.ru_maxrss / 1024 if usage else 0.0, out, [])


# ------------------------------------------------------------------------------------------------------ inputs
def events(n: int = 4689, seed: int = 0, span_us: int = 100_000) -> np.ndarray:
    """A simulated 0.1 s burst of events on a 240 x 180 sensor, file time from 1.6e15 µs (epoch-like)."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, span_us, n)) + 1_633_000_000_000_000
    ev["x"], ev["y"] = rng.integers(0, W, n), rng.integers(0, H, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    key = (ev["t"] << 20) | (ev["x"].astype(np.int64) << 8) | ev["y"]
    return ev[np.unique(key, return_index=True)[1]]


def save_npy(path: Path, ev: np.ndarray) -> Path:
    arr = np.empty(len(ev), [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    for k in ("t", "x", "y", "p"):
        arr[k] = ev[k]
    np.save(path, arr)
    return path


def save_csv(path: Path, ev: np.ndarray, seconds: bool = False) -> Path:
    t = [f"{v // 10**6}.{v % 10**6:06d}" if seconds else str(v) for v in ev["t"].tolist()]
    rows = "".join(f"{x},{y},{tt},{int(p > 0)}\n" for x, y, tt, p in zip(ev["x"].tolist(), ev["y"].tolist(), t,
                                                                         ev["p"].tolist()))
    path.write_text("x,y,t,p\n" + rows)
    return path


def evt2_flipped(folder: Path, ev: np.ndarray) -> Path:
    """An EVT2 file with one byte of one EVT_TIME_HIGH word changed (bit 20 set: its events 2^26 µs late, then time
    goes back at the next word, which the decoder takes for a wrap of its 34-bit counter: +2^34 µs from there)."""
    from eventcap.io import write_events
    from eventcap.io.prophesee import read_header

    rel = ev.copy()
    rel["t"] -= rel["t"][0]
    path = write_events(folder / "flip_evt2.raw", rel, width=W, height=H, format="evt2",
                        t_offset_us=1_633_000_000_000_000)
    _, hl = read_header(path)
    data = bytearray(path.read_bytes())
    words = np.frombuffer(bytes(data[hl:]), "<u4")
    high = np.flatnonzero(words >> 28 == 0x8)
    k = int(high[len(high) // 2])
    bit = 20
    assert not int(words[k]) >> bit & 1
    data[hl + 4 * k + bit // 8] ^= 1 << (bit % 8)
    path.write_bytes(bytes(data))
    return path


def evt3_cut(folder: Path, ev: np.ndarray, inside_group: bool) -> Path:
    """An EVT3 file cut short: inside an event group (after an ADDR_Y and a time word) or right after an event."""
    from eventcap.io import write_events

    rel = ev.copy()
    rel["t"] -= rel["t"][0]
    path = write_events(folder / f"cut_{'group' if inside_group else 'event'}_evt3.raw", rel, width=W, height=H,
                        format="evt3", t_offset_us=0)
    data = path.read_bytes()
    words = np.frombuffer(data[-200:], "<u2")
    kinds = words >> 12
    base = len(data) - 200
    if inside_group:
        i = max(i for i in range(len(words) - 1) if kinds[i] == 0x0)  # the last ADDR_Y
        cut = base + 2 * (i + 1)
        tail = np.array([next(int(w) for w in words[::-1] if w >> 12 == 0x6)], "<u2").tobytes()  # a TIME_LOW
        path.write_bytes(data[:cut] + tail)
    else:
        i = max(i for i in range(len(words) - 20) if kinds[i] == 0x2)  # an ADDR_X (an event) well before the end
        path.write_bytes(data[:base + 2 * (i + 1)])
    return path


def outliers_x(ev: np.ndarray, share: float, seed: int = 1) -> np.ndarray:
    out = ev.copy()
    rng = np.random.default_rng(seed)
    k = max(1, int(round(share * len(ev))))
    idx = rng.choice(len(ev), k, replace=False)
    out["x"][idx] = rng.integers(240, 740, k)
    return out


# ------------------------------------------------------------------------------------------------------- cases
#: bad settings for `eventcap run`: each is refused before any stage runs
BAD_SETTINGS = [
    "source.duration_s=1e308", "source.exposure_us=0", "+foo=1", "+stages.bogus.weight=1", "+source.foo=1",
    "source.fps=nan", "source.fps=0", "source.fps=-25", "source.fps=inf", "source.fps=1e308", "source.duration_s=-1",
    "source.duration_s=0", "source.duration_s=abc", "source.exposure_us=-5", "source.exposure_us=1.5",
    "source.width=0", "source.width=70000", "source.height=-1", "source.supersample=2", "source.supersample=0",
    "source.hot_pixel_fraction=2", "source.camera_tilt_deg=90", "source.camera_height_m=0",
    "source.illuminance_lux=0", "source.gt_rate_hz=0", "source.min_step_us=0", "source.n_track_points=-1",
    "source.seed=-1", "source.speed=0", "source.amplitude=-1", "source.roi=[0,0,500,500]", "source.roi=[1,2]",
    "source.camera=nope", "source.background=nope", "source.refractory_us=-1", "source.noise_rate_hz=-1",
    "source.contrast_threshold=0", "source.lens_mm=0", "source.gt_rate_hz=1e300", "source.seed=1e30",
    "stages.track.max_features=abc", "stages.track.max_features=0", "stages.track.patch_px=24",
    "stages.detect.outlier_prob=1.5", "stages.spline.knot_ms=inf", "stages.spline.knot_ms=0",
    "stages.spline.lambda_prior=-1", "stages.spline.lambda_prior=1e308", "log_level=VERBOSE", "batches=-1",
    "batches=abc", "executor=processes executor.workers=0", "executor.kind=threads", "+executor.foo=1",
    "outputs.video_fps=abc", "+outputs.foo=1", "outputs.join=sometimes",
]


def memory_rows(work: Path, n: int = 3_000_000, timeout_s: float = 300.0) -> list[dict]:
    """Peak memory of preview and convert on ``n`` events spanning 0.5 s and spanning 10 hours (npy, 240 x 180):
    what is held must not grow with the time span."""
    rows = []
    rng = np.random.default_rng(5)
    for label, span in (("0.5 s", 500_000), ("10 h", 36_000 * 10**6)):
        ev = np.empty(n, EVENT_DTYPE)
        ev["t"] = np.sort(rng.integers(0, span, n)) + 1_633_000_000_000_000
        ev["x"], ev["y"] = rng.integers(0, W, n), rng.integers(0, H, n)
        ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
        path = save_npy(work / f"span_{span}.npy", ev)
        case = f"{n / 1e6:g} M events over {label} (npy, {path.stat().st_size / 1e6:.0f} MB)"
        o = run(["preview", str(path), "--out", str(work / "m.png"), "--width", str(W), "--height", str(H)], work,
                timeout_s)
        rows.append(_table_row(case, "preview", o))
        out = work / "m.zarr"
        shutil.rmtree(out, ignore_errors=True)
        o = run(["convert", str(path), str(out), "--width", str(W), "--height", str(H)], work, timeout_s)
        rows.append(_table_row(case, "convert", o))
        shutil.rmtree(out, ignore_errors=True)
        path.unlink()
    return rows


def _table_row(case: str, how: str, o: Outcome) -> dict:
    return {"case": case, "command": how, "exit": "HANG" if o.code is None else o.code, "seconds": o.seconds,
            "peak_mb": o.peak_mb, "outcome": o.line(), "left": o.left}


def issue_table(work: Path, settings: list[str] | None = None, timeout_s: float = 60.0) -> list[dict]:
    """Run every row of issue 48's table (and the bad settings) in ``work``; one dict per command run."""
    rows: list[dict] = []
    data = work / "data"
    data.mkdir(parents=True, exist_ok=True)
    ev = events()

    def both(case: str, path: Path, *extra: str, preview: bool = True, convert: bool = True) -> None:
        if preview:
            o = run(["preview", str(path), "--out", str(work / "p.png"), *extra], work, timeout_s)
            rows.append(_table_row(case, "preview", o))
        if convert:
            out = work / "out.zarr"
            shutil.rmtree(out, ignore_errors=True)
            o = run(["convert", str(path), str(out), "--overwrite", *extra], work, timeout_s)
            rows.append(_table_row(case, "convert", o))

    wild = ev.copy()
    wild["t"][-1] = 10**12 + wild["t"][0]  # the last event 1e12 µs (11.6 days) after the first
    both("npy whose last event is at t = 1e12 us", save_npy(data / "wild_last.npy", wild))
    both("EVT2 .raw with one flipped byte (a TIME_HIGH bit)", evt2_flipped(data, ev))
    rel = ev.copy()
    rel["t"] -= rel["t"][0]
    both("CSV x,y,t,p header, integer microsecond times (from 0)", save_csv(data / "int_us.csv", rel))
    both("CSV x,y,t,p header, integer microsecond times (epoch)", save_csv(data / "int_us_epoch.csv", ev))
    both("EVT3 .raw cut inside an event group", evt3_cut(data, ev, inside_group=True))
    both("EVT3 .raw cut right after an event (cannot show)", evt3_cut(data, ev, inside_group=False))
    for share in (0.01, 0.1, 0.5, 0.9, 1.0):
        bad = outliers_x(ev, share)
        both(f"{share:.0%} of events at x = 240-739, npy of a 240 x 180 camera",
             save_npy(data / f"x_out_{int(share * 100)}.npy", bad))
        both(f"{share:.0%} of events at x = 240-739, CSV of a 240 x 180 camera",
             save_csv(data / f"x_out_{int(share * 100)}.csv", bad, seconds=True))
    fifo = data / "fifo.raw"
    if not fifo.exists():
        os.mkfifo(fifo)
    both("a FIFO with no writer", fifo)
    loop = data / "loop.aedat4"
    if not os.path.lexists(loop):
        os.symlink(loop.name, loop)
    both("a symlink loop", loop)
    for dev in ("/dev/zero", "/dev/urandom"):
        link = data / f"{Path(dev).name}.npy"
        if not os.path.lexists(link):
            os.symlink(dev, link)
        both(f"a symlink to {dev}", link)
    folder = data / "garbage_zarr"
    folder.mkdir(exist_ok=True)
    (folder / "zarr.json").write_bytes(b"\x00garbage{{{" * 10)
    both("a garbage zarr.json at a folder's root", folder)
    for setting in settings if settings is not None else BAD_SETTINGS:
        runs = work / "settings"
        shutil.rmtree(runs, ignore_errors=True)
        runs.mkdir()
        o = run(["run", "experiment=quick", *setting.split()], runs, timeout_s)
        o.left = sorted(str(p.relative_to(runs)) for p in runs.rglob("*"))
        rows.append(_table_row(setting, "run", o))
    return rows


# ------------------------------------------------------------------------- issue 57: never touch what is not ours
def listing(root: Path) -> dict[str, tuple[str, int, int]]:
    """Every path under ``root`` (links not followed): kind, size and mtime. A case may change nothing but its run
    folder and its marked cache."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            try:
                st = p.lstat()
            except FileNotFoundError:
                continue
            kind = "dir" if p.is_dir() and not p.is_symlink() else "file"
            out[str(p)] = (kind, st.st_size if kind == "file" else 0, st.st_mtime_ns if kind == "file" else 0)
    return out


def root_listing() -> dict[str, tuple[str, int, int]]:
    """The entries directly in ``/`` (never written by a case: ``hydra.run.dir=/`` once wrote three there)."""
    out = {}
    for name in os.listdir("/"):
        try:
            st = os.lstat("/" + name)
        except FileNotFoundError:
            continue
        is_dir = os.path.isdir("/" + name)  # a folder's mtime moves whenever anyone writes in it (/tmp): not ours
        out["/" + name] = ("dir" if is_dir else "file", 0 if is_dir else st.st_size, 0 if is_dir else st.st_mtime_ns)
    return out


def outside(before: dict, after: dict, allowed: list[Path]) -> list[str]:
    """Paths added, removed or changed between two listings that lie in none of the ``allowed`` folders."""
    changed = [p for p in set(before) | set(after) if before.get(p) != after.get(p)]
    ok = [str(a).rstrip("/") + "/" for a in allowed]
    # the new folders leading to an allowed one (runs/<name>/ made for the run's folder) belong to it
    made = [p for p in changed if p not in before and after[p][0] == "dir" and any(a.startswith(p + "/") for a in ok)]
    return sorted(p for p in changed if not any((p + "/").startswith(a) for a in ok) and p not in made)


#: Issue 57's settings (and accepted neighbours) for ``eventcap run``: {theirs} is someone's folder holding tmp/ and
#: trash/ (a 3-day-old file and folder in tmp/), {secret} a small text file that is no calibration, {empty} an empty
#: folder, {fresh} a folder that does not exist yet, {old} a finished run's folder. (override, expected: "refused",
#: or "accepted" on the toy pipeline, whose run folder and cache are the only places it may write)
ISSUE57_SETTINGS = [
    ("cache_dir={theirs}", "refused"), ("cache_dir=/", "refused"), ("cache_dir=/proc", "refused"),
    ("cache_dir=/sys", "refused"), ("cache_dir=/dev/null", "refused"), ("hydra.run.dir=/", "refused"),
    ("hydra.run.dir=/proc/self", "refused"), ("hydra.run.dir=/dev/null", "refused"),
    ("hydra.run.dir={theirs}", "refused"), ("hydra.run.dir=../elsewhere", "refused"),
    ("name=../../escape", "refused"), ("template.height_m=1000", "refused"), ("source.motion=", "refused"),
    ("source.motion=../../../../etc/passwd", "refused"), ("source.calibration={secret}", "refused"),
    ("source.calibration=/etc/shadow", "refused"), ("stages.detect.min_found=-0.5", "refused"),
    ("stages.detect.min_found=5", "refused"), ("source.n_track_points=1000000000", "refused"),
    ("executor=processes executor.workers=100000", "refused"),
    ("toy cache_dir={empty}", "accepted"), ("toy hydra.run.dir={fresh}", "accepted"),
    ("toy hydra.run.dir={old}", "accepted"), ("toy", "accepted"),
]


def _sandbox(root: Path) -> dict[str, Path]:
    """Fresh folders for one case: the working folder (its runs/), someone's folder, a secret, an empty folder."""
    shutil.rmtree(root, ignore_errors=True)
    places = {"work": root / "work", "theirs": root / "theirs", "empty": root / "empty", "fresh": root / "abs_run",
              "secret": root / "secret.txt", "old": root / "work" / "runs" / "earlier"}
    (places["theirs"] / "tmp" / "old_dir").mkdir(parents=True)
    (places["theirs"] / "tmp" / "old_dir" / "notes.txt").write_text("theirs")
    (places["theirs"] / "tmp" / "old.txt").write_text("theirs")
    (places["theirs"] / "trash").mkdir()
    (places["theirs"] / "trash" / "draft.doc").write_text("theirs")
    three_days = time.time() - 3 * 86400
    for p in (places["theirs"] / "tmp" / "old.txt", places["theirs"] / "tmp" / "old_dir"):
        os.utime(p, (three_days, three_days))
    places["secret"].write_text("root:$6$s3cr3tsalt$hash:19000:0:99999:7:::\n")
    places["empty"].mkdir()
    places["old"].mkdir(parents=True)
    (places["old"] / "run.json").write_text("{}")  # an earlier run's folder
    return places


def ownership_rows(work: Path, timeout_s: float = 120.0) -> list[dict]:
    """Run every case of ISSUE57_SETTINGS in a fresh sandbox and list the sandbox (and ``/``) before and after: the
    exit, the line that says what happened, and every path written or deleted outside the case's run folder and
    marked cache (must be none)."""
    from eventcap.core.ownership import check_run_folder, is_marked_cache

    rows = []
    toy = [f"hydra.searchpath=[file://{ROOT / 'tests' / 'conf'}]", "experiment=toy"]
    toy_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)]),
               "EVENTCAP_STAGES": "toy_stages:SPECS"}
    for case, expected in ISSUE57_SETTINGS:
        box = _sandbox(work / "sandbox")
        words = case.format(**{k: str(v) for k, v in box.items()}).split()
        is_toy = words[:1] == ["toy"]
        argv = ["run", *(toy + words[1:] if is_toy else ["experiment=quick", *words])]
        if "hydra.run.dir=/" in words and check_run_folder("/", "hydra.run.dir", False) is None:
            rows.append({"case": case, "command": "run", "exit": "NOT RUN", "seconds": 0.0, "peak_mb": 0.0,
                         "outcome": "the run-folder check takes /: not run", "left": ["/"]})
            continue
        env = {**(toy_env if is_toy else os.environ), "EVENTCAP_CACHE_DIR": str(box["work"] / "runs" / "cache")}
        before, before_root = listing(work / "sandbox"), root_listing()
        o = run(argv, box["work"], timeout_s, env=env)
        after, after_root = listing(work / "sandbox"), root_listing()
        allowed: list[Path] = []
        cache = next((Path(w.split("=", 1)[1]) for w in words if w.startswith("cache_dir=")),
                     box["work"] / "runs" / "cache")
        if o.code == 0:
            given = next((w.split("=", 1)[1] for w in words if w.startswith("hydra.run.dir=")), None)
            new_runs = sorted({str(Path(p).parent) for p in set(after) - set(before)
                               if Path(p).parent.parent == box["work"] / "runs" / "toy"})
            allowed = [Path(given) if given else Path(new_runs[0]) if new_runs else box["work"] / "runs" / "toy"]
            if is_marked_cache(cache):
                allowed.append(cache)
        o.left = outside(before, after, allowed) + outside(before_root, after_root, [])
        row = _table_row(case, "run", o)
        row["expected"] = expected
        rows.append(row)
    return rows


def print_ownership(rows: list[dict], file=sys.stdout) -> None:
    print("| setting | expected | exit | s | outcome | written or deleted outside the run folder and the marked cache |",
          file=file)
    print("|---|---|---|---|---|---|", file=file)
    for r in rows:
        print(f"| `{r['case']}` | {r['expected']} | {r['exit']} | {r['seconds']:.1f} | {r['outcome'][:300]} | "
              f"{len(r['left'])}{': ' + ', '.join(r['left'][:4]) if r['left'] else ''} |", file=file)
    wrong = [r for r in rows if (r["exit"] == 0) != (r["expected"] == "accepted")]
    tb = [r for r in rows if r["outcome"].startswith(("TRACEBACK", "HANG"))]
    print(f"\nissue 57's settings: {len(rows)} cases, {sum(r['exit'] not in (0, 'HANG') for r in rows)} refused, "
          f"{len(wrong)} not as expected, {len(tb)} tracebacks or hangs, "
          f"{sum(len(r['left']) for r in rows)} paths written or deleted outside a run folder or a marked cache",
          file=file)


def print_table(rows: list[dict], file=sys.stdout) -> None:
    print("| case | command | exit | s | peak MB | new outcome |", file=file)
    print("|---|---|---|---|---|---|", file=file)
    for r in rows:
        left = f" LEFT ON DISK: {', '.join(r['left'][:4])}" if r["left"] else ""
        print(f"| {r['case']} | {r['command']} | {r['exit']} | {r['seconds']:.1f} | {r['peak_mb']:.0f} | "
              f"{r['outcome'][:400]}{left} |", file=file)
    settings = [r for r in rows if r["command"] == "run"]
    if settings:
        refused = sum(r["exit"] not in (0, "HANG") for r in settings)
        left = sum(bool(r["left"]) for r in settings)
        print(f"\nbad settings: {refused} of {len(settings)} refused; {left} left anything on disk", file=file)


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds before a command counts as stuck")
    ap.add_argument("--no-settings", action="store_true", help="leave out the bad settings (eventcap run)")
    ap.add_argument("--memory-events", type=int, default=3_000_000, help="events of the memory rows (0: none)")
    ap.add_argument("--only-ownership", action="store_true", help="only issue 57's settings (sandbox listings)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="eventcap-bad-") as tmp:
        rows = [] if args.only_ownership else issue_table(Path(tmp), [] if args.no_settings else None, args.timeout)
        if args.memory_events and not args.only_ownership:
            rows += memory_rows(Path(tmp), args.memory_events)
        own = [] if args.no_settings else ownership_rows(Path(tmp), max(args.timeout, 120.0))
    if rows:
        print_table(rows)
    if own:
        print()
        print_ownership(own)
    bad = [r for r in rows if r["exit"] == "HANG" or r["outcome"].startswith(("TRACEBACK", "HANG")) or r["left"]]
    bad += [r for r in own if r["left"] or (r["exit"] == 0) != (r["expected"] == "accepted")
            or r["outcome"].startswith(("TRACEBACK", "HANG"))]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
