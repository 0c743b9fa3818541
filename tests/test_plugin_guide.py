"""docs/plugins.md, walked end to end: every file it shows is the example package's (tests/fixtures/
eventcap_postsmooth), which is then built and installed as a user would (pip, no build isolation), and the page's
commands run against it: the stage listed, its own tests passing, its pipeline composed from its own configs (the
project's conf/ untouched) and run, and evaluate measuring the whole-recording node's motion."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from helpers.paths import ROOT, TESTS

PACKAGE = TESTS / "fixtures" / "eventcap_postsmooth"
GUIDE = ROOT / "docs" / "plugins.md"
#: make the page's `eventcap run pipeline=post_smooth experiment=quick` cheaper for the test (the same pipeline)
FASTER = ["duration_s=0.09", "template=procedural", "template.target_faces=2000", "outputs.video=false"]


def shown_files() -> dict[str, str]:
    """The code blocks of the guide that show a file, by the path their first line names."""
    out = {}
    for block in re.findall(r"```[a-z]*\n(.*?)```", GUIDE.read_text(), flags=re.S):
        head = block.split("\n")[:2]  # the path's comment, after Hydra's "# @package" line in a YAML file
        m = re.fullmatch(r"# (eventcap_postsmooth/\S+)", head[1] if head[0].startswith("# @package") else head[0])
        if m:
            out[m.group(1)] = block
    return out


def guide_commands() -> list[str]:
    """The commands of the guide's bash blocks, without their comments."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", GUIDE.read_text(), flags=re.S):
        out += [line.split("  #")[0].strip() for line in block.splitlines() if line.strip()]
    return out


def test_every_file_of_the_example_package_is_on_the_page_as_it_is():
    shown = shown_files()
    files = {str(p.relative_to(PACKAGE.parent)): p.read_text() for p in sorted(PACKAGE.rglob("*")) if p.is_file()
             and "__pycache__" not in p.parts and not p.name.endswith(".egg-info")}
    assert {k for k, v in files.items() if v} == set(shown), "the guide shows another set of files than the package"
    for path, text in shown.items():
        assert text == files[path], f"{path}: the guide's block differs from tests/fixtures/{path}"
    assert files["eventcap_postsmooth/src/eventcap_postsmooth/conf/__init__.py"] == ""  # said so on the page


def _run(args, cwd, env, timeout=600):
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, args))}: exit {proc.returncode}\n{proc.stdout[-3000:]}\n" \
                                 f"{proc.stderr[-3000:]}"
    return proc


def test_the_guide_works_as_written(tmp_path):
    commands = guide_commands()
    for cmd in ("pip install ./eventcap_postsmooth", "eventcap stages post_smooth",
                "eventcap run --help pipeline=post_smooth", "eventcap run pipeline=post_smooth experiment=quick",
                "pytest eventcap_postsmooth/tests"):
        assert cmd in commands, f"the guide no longer says {cmd!r}"
    shutil.copytree(PACKAGE, tmp_path / "eventcap_postsmooth")  # a user's folder: the build writes into it
    site = tmp_path / "site"
    _run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--quiet", "--target",
          str(site), "./eventcap_postsmooth"], tmp_path, dict(os.environ))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.pop("EVENTCAP_STAGES", None)
    cli = [sys.executable, "-m", "eventcap.apps.cli"]

    listing = _run([*cli, "stages", "post_smooth"], tmp_path, env).stdout
    assert "post_smooth (v1, fuse, whole recording)" in listing and "[eventcap-postsmooth]" in listing
    assert "sigma_ms = 8.0; a finite number > 0" in listing
    usage = _run([*cli, "run", "--help", "pipeline=post_smooth"], tmp_path, env).stdout
    assert re.search(r"Pipeline post_smooth \(\S+/eventcap_postsmooth/conf/pipeline/post_smooth\.yaml, from "
                     r"eventcap-postsmooth\)", " ".join(usage.split())), usage
    assert re.search(r"\n  post_smooth +post_smooth +stages\.post_smooth +stages/post_smooth=\*gaussian", usage)

    tests = _run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "eventcap_postsmooth/tests"],
                 tmp_path, env).stdout
    assert re.search(r"\b1[0-9] passed\b", tests), tests  # the conformance suite and the package's own two

    _run([*cli, "run", "pipeline=post_smooth", "experiment=quick", *FASTER, "hydra.run.dir=runs/post"], tmp_path, env)
    run = tmp_path / "runs" / "post"
    metrics = json.loads((run / "metrics.json").read_text())
    smoothed, before = metrics["evaluate.metrics"], metrics["evaluate_unsmoothed.metrics"]
    assert smoothed["n_batches"] == 1 and before["n_batches"] > 1  # the whole motion, and the batches it came from
    assert smoothed["n_frames"] == before["n_frames"] > 0 and smoothed["AE_mm"] > 0
    assert smoothed["MPJVE_mm_s"] != before["MPJVE_mm_s"]  # the node changed the motion evaluate measured
    record = json.loads((run / "run.json").read_text())
    assert record["nodes"]["post_smooth"]["computed"] == 1
    motion = np.load(run / "motion.npz")  # the motion files follow evaluate: the smoothed motion
    assert motion["t_us"].size == smoothed["n_tracking_frames"]
    assert not (ROOT / "conf" / "pipeline" / "post_smooth.yaml").exists()


@pytest.mark.parametrize("path", ["conf/pipeline", "conf/stages"])
def test_the_projects_configs_hold_nothing_of_the_plugin(path):
    assert not list((ROOT / path).rglob("*post_smooth*"))
