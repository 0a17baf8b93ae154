"""The command line, run as a user runs it: ``python -m server ...`` in a separate process, from
the checkout, with no DRONESIM_ setting but the demo's cache."""

from __future__ import annotations

import os
import subprocess
import sys

from tests.support.paths import REPO


def run_cli(
    *args: str, env: dict | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    # The configuration comes from the arguments alone (the demo's cache location may stay).
    clean = {
        k: v
        for k, v in os.environ.items()
        if not k.upper().startswith("DRONESIM_") or k.upper() == "DRONESIM_CACHE"
    }
    return subprocess.run(
        [sys.executable, "-m", "server", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**clean, **(env or {})},
    )
