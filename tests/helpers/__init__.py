"""Shared scenes and support code of the tests: synthetic recordings, solver problems, reference readers, the fuzz and
kill/resume harnesses.

Tests import from here (``from helpers.poses import posed_recording``; pytest puts ``tests/`` on ``sys.path``), never
from another test module, ``conftest`` or a benchmark script (``tests/test_suite_rules.py`` checks it). A
benchmark script that needs a scene puts the repository root on ``sys.path`` and imports ``tests.helpers.<module>``.
The modules import ``eventcap``, the plugins and each other only, never a test module.
"""
