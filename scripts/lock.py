"""Write ``constraints.txt``: the exact versions of everything ``dronesim-ar[dev,ray]`` needs, as
installed in the environment this runs in (the one the suite passed in), for reproducible
installs: ``scripts/setup.sh`` and the Dockerfile install with ``-c constraints.txt``.

    .venv/bin/python scripts/lock.py

Only the dependency closure of the project is written (not whatever else the environment
holds); markers are evaluated for this machine, so the file is for Linux x86_64, CPython 3.11.
"""

from __future__ import annotations

import sys
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name as canonical

REPO = Path(__file__).resolve().parents[1]
PROJECT, EXTRAS = "dronesim-ar", {"dev", "ray"}


def closure() -> dict[str, str]:
    """{canonical name: installed version} for every distribution the project reaches."""
    found: dict[str, str] = {}
    todo: list[tuple[str, set[str]]] = [(PROJECT, EXTRAS)]
    seen: set[tuple[str, frozenset[str]]] = set()
    while todo:
        name, extras = todo.pop()
        key = (canonical(name), frozenset(extras))
        if key in seen:
            continue
        seen.add(key)
        try:
            dist = distribution(name)
        except PackageNotFoundError:
            # Markers were evaluated before a requirement was queued: this one applies here
            # but is not installed, and a lock without it would be incomplete.
            sys.exit(f"{name} is required but not installed: install the project first")
        if canonical(name) != PROJECT:
            found[canonical(name)] = dist.version
        for line in dist.requires or []:
            req = Requirement(line)
            wanted = [{"extra": e} for e in extras] or [{"extra": ""}]
            if req.marker is None or any(req.marker.evaluate(env) for env in wanted):
                todo.append((req.name, set(req.extras)))
    return found


def main() -> None:
    pins = closure()
    lines = [
        "# Exact versions of dronesim-ar[dev,ray]'s dependencies as tested (Linux x86_64,",
        "# CPython 3.11); written by `python scripts/lock.py`, used as pip constraints.",
        *(f"{name}=={version}" for name, version in sorted(pins.items())),
    ]
    (REPO / "constraints.txt").write_text("\n".join(lines) + "\n")
    print(f"constraints.txt: {len(pins)} pins")


if __name__ == "__main__":
    main()
