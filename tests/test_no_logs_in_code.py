"""Code comments and docstrings say why; the figures that decided it are logs, kept in docs/results/
(implementation.md, settings.md), and a stage's past versions are in git, not beside its ``version=``.

The rule for comments (:func:`log_signs`) is narrower than the help text's (tests/test_help_text.py), since comments
may state units, ranges and the geometry of a choice: it looks for a before/after between measured values ("AE 27.3
-> 27.0 mm", "0.58 -> 0.41 px", "8-10 iterations per solve instead of 20-28") and for a verdict on a run ("measured
on fast_wave", "measured better", "measured: ...").
"""

from __future__ import annotations

import ast
import io
import re
import tokenize

import pytest

from helpers.paths import ROOT

SIGNS = {
    "a before/after": re.compile(r"\d\s*(mm/s|mm|px|%|m/s|s)?\s*(->|→)\s*[+\-]?\d[\d.]*\s*(mm|px|%|m/s|s)\b"
                                 r"|\b(AE|MPJVE|error)\s+[\d.]+\s*(mm|%)?\s*(->|→)"
                                 r"|\d(\.\d+)?\s*(ms|s|mm|px|%|iterations?)\b[^.;]{0,40}instead of\s+\d"),
    "a verdict on a run": re.compile(r"\bmeasured\s*(:|better|worse|best|here\b|with\b)|\(measured[;)]|,\s*measured\)"
                                     r"|\bmeasured\s+[\d.]+|\bmeasured on (a|the|our|synthetic|fast|\w+_\w+)\b"),
}

#: Comments and docstrings as they were before the clean-up (issue 56): each must be caught.
LOGS = [
    "few pixels is silent in its band only in moments (measured on fast_wave at 10 fps, ± 20 ms: MPJVE 148 -> 138 "
    "mm/s, median peak-speed error 82% -> 76%);",
    "interior (measured on synthetic batches: 8-10 iterations per solve instead of 20-28 with the adaptive default)",
    "background around a ~10 px limb, made stitching *worse* (p90 0.58 -> 0.67 px); 6 px made it better",
    "count M a constant that unrolls the normal-equation loops (2x faster than a runtime M, measured).",
    "the short 2D points (measured 1.02-1.03 on the same captures; tried and left out).",
    "from 0.05 to 0.2 for a true c of 0.2 (measured; see benchmarks/accuracy/bench_edi.py)",
    "Estimated per parameter instead, it measured worse: with ~50 batches the small variances are too noisy.",
    "(processes), and oversubscribed BLAS threads made small per-frame products 5-10x slower here (a dense Cholesky "
    "took 1.4 s instead of 49 ms with two threads fighting on a busy 2-core machine)",
]

#: Comments that state what code does, a unit, a ramp or an example: none may be caught.
PLAIN = [
    "Quintic 0->1 on [0, 1] with zero velocity and acceleration at both ends.",
    "Readable differences between two key documents: ``config.window: 3 -> 5``.",
    "evidence is measured on request through :meth:`evidence`.",
    "the measured segments (:data:`SEGMENTS`): upper arms, forearms, thighs and shins",
    "(x, y, z) -> (x, -z, y)",
    "the unknowns are the n_seg + 3 control points instead of 1,000 poses per second",
]


def log_signs(text: str) -> list[str]:
    return [name for name, rx in SIGNS.items() if rx.search(text)]


def comments_and_docstrings(path):
    """(line, text) of every comment block (consecutive comment lines joined) and docstring paragraph of a file."""
    src = path.read_text()
    block, start, last = [], None, None
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type != tokenize.COMMENT:
            continue
        if last is not None and tok.start[0] != last + 1:
            yield start, " ".join(block)
            block, start = [], None
        start = start or tok.start[0]
        block.append(tok.string.lstrip("#: ").strip())
        last = tok.start[0]
    if block:
        yield start, " ".join(block)
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                for para in re.split(r"\n\s*\n", doc):
                    yield node.body[0].lineno, " ".join(para.split())


def sources():
    for base in ("eventcap", "plugins"):
        yield from sorted((ROOT / base).rglob("*.py"))


@pytest.mark.parametrize("text", LOGS, ids=range(len(LOGS)))
def test_the_rule_catches_each_log(text):
    assert log_signs(text), text


@pytest.mark.parametrize("text", PLAIN, ids=range(len(PLAIN)))
def test_the_rule_leaves_plain_comments_alone(text):
    assert log_signs(text) == [], text


def test_no_comment_or_docstring_carries_a_measurement_log():
    found = [f"{p.relative_to(ROOT)}:{line}: {', '.join(signs)}: {text[:160]}" for p in sources()
             for line, text in comments_and_docstrings(p) if (signs := log_signs(text))]
    assert not found, ("comments say why; move the figures to docs/results/implementation.md (with the commit that "
                       "measured them) and point there:\n" + "\n".join(found))


def test_no_stage_version_carries_its_history():
    rx = re.compile(r"\bversion=\d+,\s*#")
    found = [f"{p.relative_to(ROOT)}:{i}" for p in sources() for i, line in enumerate(p.read_text().splitlines(), 1)
             if rx.search(line)]
    assert not found, "a stage's past versions are in git (git log -S 'version=N' FILE), not in a comment: " + \
        ", ".join(found)
