"""The docs name only files that are in the repository.

Scans README.md and docs/**/*.md for relative Markdown links (``[text](path)``, resolved from the file's folder) and for
repository paths in code (inline backticks and fenced blocks: ``benchmarks/x.py``, ``conf/...yaml``, ``docs/x.md``,
``eventcap/...py``, ``plugins/...``, ``tests/...``, ``tools/...``), resolved from the repository's root, and asserts
each exists. Paths under ``runs/`` (made by runs) and paths with a placeholder (``<name>``, ``*``, ``{a,b}``,
``...``) are not checked.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

#: top-level folders whose paths the docs name in code
PREFIXES = ("benchmarks", "conf", "docs", "eventcap", "plugins", "tests", "tools")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^ *```.*?^ *```", re.S | re.M)  # also indented (in a list)
INLINE = re.compile(r"`([^`]+)`")  # may span lines, as Markdown allows
PATH = re.compile(r"(?<![\w./<>-])((?:%s)/[^\s`'\"),;:]*)" % "|".join(PREFIXES))
PLACEHOLDER = re.compile(r"[<>*{}]|\.\.\.|\bNN\b")


def code_spans(text: str) -> list[str]:
    """The text of every fenced block and inline code span."""
    fenced = FENCE.findall(text)
    rest = FENCE.sub("", text)
    return fenced + INLINE.findall(rest)


def references(doc: Path) -> list[tuple[str, Path]]:
    """(what the doc says, the path it means) for every relative link and repository path in code."""
    text = doc.read_text(encoding="utf-8")
    out = []
    for target in LINK.findall(FENCE.sub("", text)):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (https:, mailto:) or an anchor in the same page
        path = target.split("#", 1)[0]
        if path and not PLACEHOLDER.search(path):
            out.append((target, (doc.parent / path).resolve()))
    for span in code_spans(text):
        for token in PATH.findall(span):
            token = token.rstrip(".")
            if PLACEHOLDER.search(token) or token.startswith("runs/"):
                continue
            out.append((token, ROOT / token))
    return out


def test_the_scanner_finds_links_and_paths_and_skips_placeholders(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("See [a](docs/a.md#part), [web](https://x.org) and [here](#top).\n"
                   "Run `python benchmarks/b.py --x 1`, `conf/stages/<node>/<v>.yaml`, `plugins/*/spec.py`,\n"
                   "`eventcap.energy` and `stages/detect=file`.\n```bash\npython tools/t.py runs/x/y.npz\n```\n"
                   "- a list item:\n\n  ```bash\n  python tools/u.py\n  ```\n- `conf/x.yaml` after it\n")
    said = [s for s, _ in references(doc)]
    assert said == ["docs/a.md#part", "tools/t.py", "tools/u.py", "benchmarks/b.py", "conf/x.yaml"]


@pytest.mark.parametrize("doc", DOCS, ids=[str(d.relative_to(ROOT)) for d in DOCS])
def test_every_file_a_doc_names_exists(doc):
    missing = sorted({said for said, path in references(doc) if not path.exists()})
    assert not missing, f"{doc.relative_to(ROOT)} names files that are not in the repository: {missing}"
