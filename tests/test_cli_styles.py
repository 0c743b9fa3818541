"""One settings style across the CLI (issue 38): every subcommand takes ``key=value`` as well as ``--key value``, an
unknown setting is named with the ones there are, and asking for something that does not exist exits non-zero."""

from __future__ import annotations

import pytest

from eventcap.apps.cli import main, run_options_as_overrides


def test_cache_ls_takes_both_styles_and_a_missing_cache_is_an_error(tmp_path, capsys):
    missing = tmp_path / "nope"
    for argv in (["cache", "ls", f"cache_dir={missing}"], ["cache", "ls", "--cache-dir", str(missing)],
                 ["cache", "ls", f"cache-dir={missing}"]):
        assert main(argv) == 2
        assert f"{missing} does not exist" in capsys.readouterr().err


def test_cache_ls_and_explain_of_an_existing_cache(tmp_path, capsys):
    from eventcap.core.cache import Cache

    Cache(tmp_path / "cache")  # an empty cache
    assert main(["cache", "ls", f"cache_dir={tmp_path / 'cache'}"]) == 0
    assert "0 entries" in capsys.readouterr().out
    assert main(["cache", "explain", "abcdef", f"cache_dir={tmp_path / 'cache'}"]) == 2  # an unknown key
    assert "no cache entry with key 'abcdef'" in capsys.readouterr().err


def test_an_unknown_setting_is_named_with_the_ones_there_are(capsys):
    with pytest.raises(SystemExit) as err:
        main(["cache", "ls", "cache_dri=x"])
    assert str(err.value) == "eventcap cache: unknown setting 'cache_dri' (settings: all, cache_dir, older_than); did " \
                             "you mean cache_dir=...?"
    with pytest.raises(SystemExit, match="all: expected true or false, got 'maybe'"):
        main(["cache", "gc", "all=maybe"])


def test_missing_run_and_sweep_folders_exit_non_zero(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert main(["view", str(tmp_path / "nope"), "no_open=true"]) == 2
    assert "expected a run folder" in capsys.readouterr().err


def test_run_takes_the_option_style_too():
    assert run_options_as_overrides(["--cache-dir", "/c", "experiment=quick", "--log-level=DEBUG", "-m"]) == \
        ["cache_dir=/c", "experiment=quick", "log_level=DEBUG", "-m"]
