"""The repository's code and docs speak in their own terms: no tracker numbers, no sections of documents a reader of
the repository does not have (design brief, research notes), no paths outside it."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# (written with character classes so that a plain search of the repository for these names finds no false hit here)
FOREIGN = re.compile(r"\bissue[ ]\d+|[(]issue|DESIGN[ ]§|DESIGN[.]md|shared/[r]eference|[r]esearch/|spec[ ]§|zenoh[.]md"
                     r"|ecosystem[.]md", re.IGNORECASE)
SUFFIXES = {".py", ".md", ".toml", ".yml", ".yaml", ".json5", ".cfg"}
SKIP_DIRS = {".git", ".venv", "runs", "node_modules", "build", "dist", ".hypothesis", ".pytest_cache", ".ruff_cache"}
# The checks that keep such text out of user-facing messages name the patterns they look for.
ALLOWED = {"tests/test_cli_messages.py", "tests/test_repo_text.py"}


def _texts():
    for path in sorted(ROOT.rglob("*")):
        rel = path.relative_to(ROOT)
        if any(part in SKIP_DIRS or part.endswith(".egg-info") for part in rel.parts):
            continue
        if path.is_file() and (path.suffix in SUFFIXES or path.name in {"Dockerfile", "run"}):
            if rel.as_posix() not in ALLOWED:
                yield rel.as_posix(), path.read_text(encoding="utf-8", errors="replace")


def test_code_and_docs_cite_nothing_a_reader_does_not_have():
    found = [f"{rel}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)}"
             for rel, text in _texts() for m in FOREIGN.finditer(text)]
    assert not found, "references a reader of the repository cannot follow:\n" + "\n".join(found)


def test_the_check_sees_the_docs_and_the_code():
    seen = {rel for rel, _ in _texts()}
    assert {"README.md", "docs/decisions.md", "services/sim/service.py", "pyproject.toml"} <= seen


def test_on_loadgroup_workers_every_test_carries_its_group(request):
    """tests/conftest.py groups the tests by file (and the users of a shared live run together) for pytest-xdist's
    ``--dist loadgroup``, which marks the group in the test's id. A pytest or xdist release that drops it does so
    silently: a file's tests and a shared live run would be spread over the workers (seen with pytest 9.2)."""
    if not os.environ.get("PYTEST_XDIST_WORKER") or not request.config.getoption("loadgroup", False):
        pytest.skip("not on a --dist loadgroup worker")
    assert request.node.nodeid.endswith("@test_repo_text"), request.node.nodeid
