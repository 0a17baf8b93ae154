"""Which code a benchmark ran: the commit every results file records (a light module, so that
a benchmark that only times other processes needs none of the heavy imports)."""

from __future__ import annotations

import subprocess
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def git_commit() -> str:
    """The short HEAD commit, with " + uncommitted changes" when server/ or benchmarks/ differ
    from it."""

    def git(*a: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *a], cwd=REPO_ROOT, capture_output=True, text=True)

    try:
        head = git("rev-parse", "--short", "HEAD").stdout.strip() or "unknown"
        dirty = git("diff", "--quiet", "HEAD", "--", "server", "benchmarks").returncode != 0
    except OSError:
        return "unknown"
    return head + (" + uncommitted changes" if dirty else "")
