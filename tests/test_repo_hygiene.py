"""The repository cites only what it holds or names a primary source: no pointers to files outside it."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SKIP = {".git", ".venv", "__pycache__", "node_modules"}
OFF_REPO = re.compile(r"facts\.md|design\.md|design notes|\.\./shared", re.IGNORECASE)


def repo_files(*suffixes: str) -> list[Path]:
    """Files of the repository (not the virtualenv or git's own) whose name ends in one of suffixes."""
    return [p for p in REPO.rglob("*") if p.is_file() and p.suffix in suffixes
            and not SKIP.intersection(p.relative_to(REPO).parts)]


def test_no_file_cites_a_file_outside_the_repository():
    this = Path(__file__).resolve()
    found = [f"{p.relative_to(REPO)}:{n}: {line.strip()}"
             for p in repo_files(".py", ".md", ".yaml", ".yml") if p.resolve() != this
             for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1)
             if OFF_REPO.search(line)]
    assert not found, "off-repository citations:\n" + "\n".join(found)
