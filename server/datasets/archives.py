"""An iPhone recording that arrived as one file (an upload): a Record3D ``.r3d`` or a Stray
Scanner export zipped, told apart by what the zip holds, never by its name.

A Record3D file is read in place (it is a zip already). A Stray export is unpacked into a folder
first (OpenCV reads the video from a file), member by member under names this module makes
itself, and only after the sizes the zip declares passed ``max_unpacked_bytes``: a zip whose
names climb out of the folder or whose contents would fill the disk unpacks nothing.
"""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path, PurePosixPath

from server.datasets.base import RGBDDataset
from server.datasets.bounds import DEFAULT_LIMITS, DecodeLimits
from server.datasets.record3d import Record3DDataset
from server.datasets.stray import StrayDataset
from server.errors import DatasetError

STRAY_FILES = ("rgb.mp4", "odometry.csv", "camera_matrix.csv")
STRAY_FOLDERS = ("depth", "confidence")


class UnknownRecording(DatasetError):
    """The file is not a zip, or a zip of neither a Record3D nor a Stray Scanner recording."""


def _stray_root(names: list[str]) -> str | None:
    """The folder inside the zip that holds a Stray export ('' for the top, 'scan/' for one
    folder down), or None when there is none."""
    for name in names:
        path = PurePosixPath(name)
        if path.name == "odometry.csv" and len(path.parts) <= 2:
            root = "" if len(path.parts) == 1 else f"{path.parts[0]}/"
            if f"{root}rgb.mp4" in names:
                return root
    return None


def open_recording_archive(
    path: Path, unpack_to: Path, max_unpacked_bytes: int, limits: DecodeLimits = DEFAULT_LIMITS
) -> RGBDDataset:
    """The recording in the file ``path``: a Record3DDataset on it, or a StrayDataset on its
    contents unpacked into the (new) folder ``unpack_to``; either reads within ``limits``.

    Raises UnknownRecording for a file that is neither, DatasetError for one that is but cannot
    be read (then ``unpack_to`` may hold part of it: the caller removes it)."""
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            names = [i.filename for i in infos]
            if "metadata" in names and any(n.startswith("rgbd/") for n in names):
                return Record3DDataset(path, limits=limits)
            root = _stray_root(names)
            if root is None:
                raise UnknownRecording(
                    "the zip holds neither a Record3D recording (metadata, rgbd/) nor a Stray "
                    "Scanner export (rgb.mp4, odometry.csv, camera_matrix.csv, depth/)"
                )
            wanted = [i for i in infos if _stray_member(i.filename, root) is not None]
            total = sum(i.file_size for i in wanted)
            if total > max_unpacked_bytes:
                raise DatasetError(
                    f"the Stray export unpacks to {total / 1e6:.0f} MB, more than the "
                    f"{max_unpacked_bytes / 1e6:.0f} MB allowed "
                    "(a multiple of server.max_upload_mb)"
                )
            unpack_to.mkdir(parents=True)
            for folder in STRAY_FOLDERS:
                (unpack_to / folder).mkdir()
            for info in wanted:
                relative = _stray_member(info.filename, root)
                assert relative is not None
                with archive.open(info) as src, (unpack_to / relative).open("wb") as dst:
                    shutil.copyfileobj(src, dst, 1 << 20)
    except zipfile.BadZipFile as exc:
        raise UnknownRecording(f"not a zip file (a .r3d or a zipped Stray export): {exc}") from exc
    except (OSError, RuntimeError, NotImplementedError) as exc:  # encrypted, odd compression
        raise DatasetError(f"cannot unpack the zip: {exc}") from exc
    return StrayDataset(unpack_to, limits=limits)


def _stray_member(name: str, root: str) -> str | None:
    """The relative path a zip member unpacks to ('depth/000001.png'), or None for a member the
    loader does not read; only plain names of the export's own files and folders pass."""
    if not name.startswith(root):
        return None
    parts = PurePosixPath(name[len(root) :]).parts
    if len(parts) == 1 and parts[0] in STRAY_FILES:
        return parts[0]
    if (
        len(parts) == 2
        and parts[0] in STRAY_FOLDERS
        and parts[1].endswith(".png")
        and parts[1][:-4].isdigit()
    ):
        return f"{parts[0]}/{parts[1]}"
    return None
