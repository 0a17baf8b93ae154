"""Which code a benchmark ran: the commit every results file records (a light module, so that
a benchmark that only times other processes needs none of the heavy imports)."""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import subprocess
import sys
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


def utc_stamp() -> str:
    """Now, as the results files date their runs."""
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def run_heading(stamp: str, note: str = "") -> list[str]:
    """A results file's heading for this run: date and commit, the command line, the machine
    (``note`` after it, e.g. ", one thread"), and a blank line before the table."""
    command = shlex.join(["python", *sys.argv])
    return [
        f"\n## {stamp}, commit {git_commit()}",
        f"`{command}`; {platform.platform()}, {os.cpu_count()} CPUs{note}\n",
    ]
