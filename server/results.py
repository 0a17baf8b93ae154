"""Where ``track`` puts its results: one new folder per run under a parent, and ``latest``.

As kiss-icp does: ``track DATASET --out results/track`` writes into
``results/track/<dataset>_<YYYY-MM-DD_HH-MM-SS>/`` (a suffix ``_2``, ``_3``... when that
exists already), so no run overwrites another, and points the symbolic link
``results/track/latest`` at it (relative, replaced atomically), so that scripts and
``--room`` can name the newest run without knowing its time.
"""

from __future__ import annotations

import logging
import os
import re
import time
from pathlib import Path

from server.errors import DroneSimError
from server.rooms.room import META_FILE as ROOM_META

log = logging.getLogger(__name__)

LATEST = "latest"
ROOM = "room"  # a run's room folder (server/rooms/room.py)
SUMMARY = "summary.json"  # in every run's folder (server/pipeline.py: write_outputs)


class ResultsError(DroneSimError):
    """A results folder that cannot be made or read as asked."""


def run_folder_name(dataset_name: str, when: float | None = None) -> str:
    """``<dataset>_<YYYY-MM-DD_HH-MM-SS>`` (local time), the name made safe for file systems."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "-", dataset_name).strip("-.") or "run"
    return f"{safe}_{time.strftime('%Y-%m-%d_%H-%M-%S', time.localtime(when))}"


def new_run_folder(parent: str | Path, dataset_name: str, when: float | None = None) -> Path:
    """Make and return a new, empty run folder under ``parent`` (made too)."""
    parent = Path(parent)
    if parent.name == LATEST or (parent / SUMMARY).is_file():
        raise ResultsError(
            f"--out {parent} is a run's folder; give the folder that holds the runs "
            f"({parent.parent}), each run gets a new folder in it"
        )
    parent.mkdir(parents=True, exist_ok=True)
    base = run_folder_name(dataset_name, when)
    for n in range(1, 1000):
        folder = parent / (base if n == 1 else f"{base}_{n}")
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        return folder
    raise ResultsError(f"{parent} already holds 999 runs named {base}")


def link_latest(run: Path) -> Path | None:
    """Point ``<parent>/latest`` at ``run`` (relative link, swapped in by one rename, so a
    reader sees the old run or the new one); the link, or None where the file system has no
    symbolic links (logged)."""
    link = run.parent / LATEST
    if link.exists() and not link.is_symlink():
        raise ResultsError(f"{link} is not a link: move it away to keep track of the latest run")
    tmp = run.parent / f".{LATEST}.{os.getpid()}.tmp"
    try:
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(run.name, target_is_directory=True)
        os.replace(tmp, link)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        log.warning("could not link %s to %s: %s", link, run, exc)
        return None
    return link


def room_folder(path: str | Path) -> Path:
    """The room an earlier run saved, from any of: its room folder, its run folder, or the
    folder that holds the runs (then its ``latest``)."""
    path = Path(path)
    for folder in (path, path / ROOM, path / LATEST / ROOM):
        if (folder / ROOM_META).is_file():
            return folder
    raise ResultsError(
        f"no room at {path}: give a run's folder (or its {ROOM}/ folder), or the --out folder "
        f"of earlier runs (its {LATEST} run is taken)"
    )
