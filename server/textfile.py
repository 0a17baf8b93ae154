"""Line-oriented text files (TUM lists and trajectories): comments start with '#'."""

from __future__ import annotations

from pathlib import Path

from server.errors import DroneSimError


def data_lines(path: Path, error: type[DroneSimError], what: str = "") -> list[tuple[int, str]]:
    """(line number from 1, stripped text) of every non-empty, non-comment line of ``path``.
    Raises ``error`` naming ``what`` and the file when it cannot be read."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise error(f"cannot read {what}{path}: {exc.strerror}") from exc
    stripped = ((n, raw.strip()) for n, raw in enumerate(text.splitlines(), start=1))
    return [(n, line) for n, line in stripped if line and not line.startswith("#")]
