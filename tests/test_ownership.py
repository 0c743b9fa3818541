"""The tool writes and deletes only what it made (issue 57 items 1-2, issue 56 item 6): a cache carries its marker
and clean-up acts only inside it, on names it writes; a run folder is fresh or its own, inside runs/ when given
relative; every setting, the paths among them, is checked before the run folder exists; a finished run leaves no
lock file and a failed one no empty metrics.json; a sweep prints its folder.

Each case that runs the tool lists a sandbox folder before and after: nothing outside the marked cache and the run
folder may appear, change or vanish."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from eventcap.apps.jobs import check_places, preflight
from eventcap.core.cache import Cache, CacheError, check_cache_root
from eventcap.core.ownership import CACHE_TAG, check_run_folder, is_marked_cache, system_folder
from eventcap.core.rundir import LOCK_NAME, RunFolderRefused, claim, release

from helpers.paths import TESTS
from helpers.runs import small_capture_config
from helpers.toy import toy_env

TOY = [f"hydra.searchpath=[file://{TESTS / 'conf'}]", "experiment=toy"]
KEY = "0123456789abcdef0123456789abcdef01234567"


def listing(root: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``root`` with its size and mtime (what a run may not touch outside its own folders)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            out[str(p.relative_to(root))] = (st.st_size if not p.is_dir() else 0, st.st_mtime_ns)
    return out


def someones_folder(root: Path) -> Path:
    """A folder of someone else's holding tmp/ and trash/ (the issue's case): a 3-day-old file and folder in tmp/."""
    (root / "tmp" / "old_dir").mkdir(parents=True)
    (root / "tmp" / "old_dir" / "notes.txt").write_text("mine")
    (root / "tmp" / "old.txt").write_text("mine")
    (root / "trash").mkdir()
    (root / "trash" / "draft.doc").write_text("mine too")
    three_days = time.time() - 3 * 86400
    for p in (root / "tmp" / "old.txt", root / "tmp" / "old_dir"):
        os.utime(p, (three_days, three_days))
    return root


# ------------------------------------------------------------------------------------------------------ caches
def test_a_folder_that_is_not_a_cache_is_refused_and_nothing_in_it_deleted(tmp_path):
    folder = someones_folder(tmp_path / "theirs")
    before = listing(folder)
    for make in (lambda: Cache(folder), lambda: Cache(folder, create=False), lambda: check_cache_root(folder)):
        with pytest.raises(CacheError, match=r"is not an eventcap cache \(it has no CACHEDIR.TAG written by eventcap\)"
                                             r" and it is not empty \(it holds tmp, trash\)"):
            make()
    assert listing(folder) == before


def test_a_new_cache_is_marked_and_cleans_only_names_it_writes(tmp_path):
    cache = Cache(tmp_path / "c")
    assert is_marked_cache(cache.root) and (cache.root / CACHE_TAG).read_text().startswith("Signature: 8a477f597d")
    ours = cache.root / "tmp" / f"{KEY}.somehost.1.abcdef01"  # another host: removed when old
    ours.mkdir()
    theirs = cache.root / "tmp" / "holiday_photos"
    theirs.mkdir()
    trash_ours = cache.root / "trash" / f"{KEY}.abcdef01"
    trash_ours.mkdir()
    trash_theirs = cache.root / "trash" / "letter.txt"
    trash_theirs.write_text("x")
    days_ago = time.time() - 3 * 86400
    for p in (ours, theirs):
        os.utime(p, (days_ago, days_ago))
    removed = cache.clean_orphans()
    assert sorted(p.name for p in removed) == sorted([ours.name, trash_ours.name])
    assert theirs.is_dir() and trash_theirs.read_text() == "x"


def test_an_empty_folder_becomes_a_cache_and_an_old_cache_is_recognised(tmp_path):
    (tmp_path / "empty").mkdir()
    assert is_marked_cache(Cache(tmp_path / "empty").root)
    old = tmp_path / "old"  # a cache made before markers existed: its folders and names only
    for sub in ("entries/edi", "tmp", "failures", "trash", "locks"):
        (old / sub).mkdir(parents=True)
    (old / "entries" / "edi" / KEY).mkdir()
    (old / "failures" / f"{KEY}.json").write_text("{}")
    (old / "tmp" / f"{KEY}.host.12.abcdef01").mkdir()
    assert not is_marked_cache(old)
    Cache(old, create=False)  # inspecting it writes nothing
    assert not is_marked_cache(old)
    Cache(old)
    assert is_marked_cache(old) and (old / "entries" / "edi" / KEY).is_dir()
    (old / "tmp" / "mine.txt").write_text("x")  # a marked cache stays one whatever lands in it
    Cache(old)


def test_a_folder_holding_only_empty_tmp_and_trash_is_not_an_old_cache(tmp_path):
    """Only an old cache's full layout (entries, tmp, failures, trash) or a lone locks/ of a cache being made counts
    as a cache without its marker: someone's empty tmp/ and trash/ are refused and nothing is written there."""
    folder = tmp_path / "theirs"
    for sub in ("tmp", "trash"):
        (folder / sub).mkdir(parents=True)
    with pytest.raises(CacheError, match=r"is not an eventcap cache .* \(it holds tmp, trash\)"):
        Cache(folder)
    assert sorted(os.listdir(folder)) == ["tmp", "trash"]
    (tmp_path / "being_made" / "locks").mkdir(parents=True)
    (tmp_path / "being_made" / "locks" / f"{KEY}.lock").write_text("")
    assert is_marked_cache(Cache(tmp_path / "being_made").root)


@pytest.mark.parametrize("given, why", [("/", "the root of the filesystem"), ("/proc", "a folder of the kernel"),
                                        ("/sys", "a folder of the kernel"), ("/dev/null", "a folder of the kernel"),
                                        ("/etc", "a folder of the operating system"),
                                        ("/tmp", "a folder shared by everyone")])
def test_system_folders_are_never_a_cache(given, why):
    with pytest.raises(CacheError, match=f"cache_dir {given}: .*{why}"):
        check_cache_root(given)


def test_a_file_is_not_a_cache(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(CacheError, match="is a file, not a directory"):
        check_cache_root(tmp_path / "f")


# ------------------------------------------------------------------------------------------------- run folders
@pytest.mark.parametrize("given, why", [("/", "the root of the filesystem"),
                                        ("/proc/self", r"/proc/self \(that is /proc/\d+\) is under /proc"),
                                        ("/dev/null", "under /dev, a folder of the kernel"),
                                        ("/usr/local", "under /usr, a folder of the operating system"),
                                        ("/home", "a folder shared by everyone")])
def test_system_folders_are_never_a_run_folder(given, why):
    problem = check_run_folder(given, "hydra.run.dir", given_relative=False)
    assert problem is not None and problem.startswith("hydra.run.dir: ")
    assert __import__("re").search(why, problem)
    with pytest.raises(RunFolderRefused):
        claim(given, key="hydra.run.dir")


def test_run_folder_rules(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    theirs = someones_folder(tmp_path / "theirs")
    (tmp_path / "afile").write_text("x")
    (tmp_path / "empty").mkdir()
    assert "no eventcap run made and it is not empty (it holds tmp, trash)" in check_run_folder(theirs, "k", False)
    assert "exists and is not a folder" in check_run_folder(tmp_path / "afile", "k", False)
    assert check_run_folder(tmp_path / "empty", "k", False) is None
    assert check_run_folder(tmp_path / "new" / "deep", "k", False) is None
    assert "lies outside the runs folder" in check_run_folder("../escape", "name", True)
    assert "lies outside the runs folder" in check_run_folder("runs", "hydra.run.dir", True)  # the root itself
    assert check_run_folder("runs/a/b", "hydra.run.dir", True) is None
    # an earlier run's folder (its lock file gone) may be run into again
    folder = claim(tmp_path / "mine")
    (folder / "run.json").write_text("{}")
    release(folder)
    assert not (folder / LOCK_NAME).exists()
    assert check_run_folder(folder, "k", False) is None
    assert claim(folder) == folder
    release(folder)


def test_name_and_cache_dir_are_checked_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"name='\.\./\.\./escape': expected the experiment's folder name inside runs/"):
        check_places({"name": "../../escape", "cache_dir": str(tmp_path / "c")})
    with pytest.raises(ValueError, match="cache_dir /proc: /proc is under /proc"):
        check_places({"name": "x", "cache_dir": "/proc"})
    assert not (tmp_path / "c").exists()


# ---------------------------------------------------------------------------------- settings before the run folder
def _with(data: dict, dotted: str, value) -> dict:
    d = copy.deepcopy(data)
    node = d
    *parents, last = dotted.split(".")
    for part in parents:
        node = node[part]
    node[last] = value
    return d


def test_the_issues_settings_are_refused_before_the_run_folder_naming_the_key(tmp_path):
    """The cases of issue 57 that were refused only after the run folder existed, or accepted out of range."""
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$s3cr3tsalt$verysecrethash:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\n")
    data = small_capture_config()
    cases = {
        ("template.height_m", 1000): "template.height_m: expected a finite number in [1, 2.3], got 1000",
        ("source.motion", ""): "source.motion: give at least one motion name",
        ("source.motion", "../../../../etc/passwd"): "source.motion: unknown motion '../../../../etc/passwd'",
        ("source.motion", "missing.bvh"): "source.motion: missing.bvh: no such file or folder",
        ("source.calibration", str(secret)): f"source.calibration: {secret}: expected exactly one calibration line",
        ("source.calibration", str(tmp_path)): "source.calibration: ",
        ("source.calibration", "/dev/zero"): "source.calibration: /dev/zero is under /dev, a folder of the kernel",
        ("cache_dir", "/proc"): "cache_dir /proc: /proc is under /proc, a folder of the kernel",
        ("cache_dir", "/sys"): "cache_dir /sys: /sys is under /sys",
        ("cache_dir", "/dev/null"): "cache_dir /dev/null: /dev/null is under /dev",
        ("source.n_track_points", 10**9): "source.n_track_points: expected an integer in [0, 10000], got 1000000000",
        ("executor.workers", 100000): "executor.workers: expected an integer in [1, 256], got 100000",
    }
    for (key, value), message in cases.items():
        with pytest.raises(ValueError) as err:
            preflight(_with(data, key, value))
        assert message in str(err.value), (key, value, str(err.value))
        assert "s3cr3t" not in str(err.value) and "root:" not in str(err.value)
    # the template's own stature (anny's range) and detect's share, in the default pipeline
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(TESTS.parent / "conf"), version_base="1.3"):
        default = OmegaConf.to_container(compose(config_name="config", overrides=["experiment=quick"]), resolve=True)
    for value in (-0.5, 5):
        with pytest.raises(ValueError, match=rf"stages.detect.min_found: expected a finite number in \[0, 1\], "
                                             rf"got {value}"):
            preflight(_with(default, "stages.detect.min_found", value))
    with pytest.raises(ValueError, match=r"template.height_m: expected a finite number in \[1.2, 2.3\], got 1000"):
        preflight(_with(default, "template.height_m", 1000))


# ---------------------------------------------------------------------------------------------- through the CLI
def cli(args, cwd, env=None):
    return subprocess.run([sys.executable, "-m", "eventcap.apps.cli", *args], cwd=cwd, env=env or toy_env(),
                          capture_output=True, text=True, timeout=300)


def test_refused_runs_leave_the_sandbox_as_it_was(tmp_path):
    """Each refused case through the real CLI: exit non-zero, one line naming the key, not a file written or deleted
    anywhere in the sandbox (the work folder, someone's folder, the cache)."""
    work = tmp_path / "work"
    work.mkdir()
    theirs = someones_folder(tmp_path / "theirs")
    env = {**toy_env(), "EVENTCAP_CACHE_DIR": str(tmp_path / "cache")}
    cases = [(f"cache_dir={theirs}", "is not an eventcap cache"),
             (f"hydra.run.dir={theirs}", "is a folder that no eventcap run made"),
             ("name=../../escape", "name='../../escape'"),
             ("hydra.run.dir=../outside", "lies outside the runs folder"),
             ("hydra.run.dir=/proc/self", "a folder of the kernel"),
             ("hydra.run.dir=/dev/null", "a folder of the kernel")]
    for override, message in cases:
        before = listing(tmp_path)
        p = cli(["run", *TOY, override], work, env)
        out = p.stdout + p.stderr
        assert p.returncode != 0 and message in out and "Traceback" not in out and "Errno" not in out, (override, out)
        assert listing(tmp_path) == before, override


def test_a_finished_run_leaves_no_lock_and_a_failed_one_no_empty_metrics(tmp_path):
    p = cli(["run", *TOY, "hydra.run.dir=runs/ok"], tmp_path)
    assert p.returncode == 0, p.stderr
    folder = tmp_path / "runs" / "ok"
    assert not (folder / LOCK_NAME).exists() and (folder / "metrics.json").is_file()
    assert is_marked_cache(tmp_path / "runs" / "cache")
    p = cli(["run", *TOY, "hydra.run.dir=runs/failed", "stages.smooth.fail_batches=[1]",
             "cache_dir=runs/fresh_cache"], tmp_path)
    failed = tmp_path / "runs" / "failed"
    assert p.returncode == 1 and not (failed / LOCK_NAME).exists() and not (failed / "metrics.json").exists()
    assert (failed / "run.json").is_file()


def test_a_sweep_prints_its_folder(tmp_path):
    p = cli(["run", "-m", *TOY, "stages.scale.factor=1,2"], tmp_path)
    sweep = next((tmp_path / "runs" / "toy").glob("multirun_*"))
    rel = sweep.relative_to(tmp_path)
    assert f"sweep folder {rel}/: 2 job folder(s); one table of them: eventcap report {rel}" in p.stdout + p.stderr
    assert not (sweep / LOCK_NAME).exists() and not any((sweep / j / LOCK_NAME).exists() for j in ("0", "1"))


def test_system_folder_words():
    assert system_folder("/") == "/ is the root of the filesystem"
    assert system_folder("/etc") == "/etc is a folder of the operating system"
    assert system_folder(Path.home() / "some" / "project") is None
