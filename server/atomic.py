"""Atomic file writes: a reader sees a file's old content or its new one, never half of it.

Session snapshots, TSDF maps, trajectories and the TLS key all go through ``atomic_write``.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path


def atomic_write(
    path: str | Path,
    write: Callable[[str], object],
    *,
    suffix: str = ".tmp",
    mode: int | None = None,
    durable: bool = False,
) -> None:
    """Call ``write(tmp_path)`` on a new temporary file beside ``path``, then rename it over
    ``path``; on any failure the temporary file is removed and ``path`` is left as it was.

    The file is made in the same folder, so the rename stays on one file system (atomic).
    suffix: the temporary file's ending (writers such as Open3D pick the format from it).
    mode: permission bits of the result; None keeps mkstemp's owner-only 0o600.
    durable: flush the data to disk before the rename, so a power loss cannot leave an empty
    file under the new name.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        if durable:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | Path, data: bytes, *, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` atomically and durably (owner-only unless ``mode``)."""
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data), mode=mode, durable=True)
