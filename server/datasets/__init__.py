"""RGB-D sequence loaders behind one interface, chosen by name or by sniffing the path."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from server.datasets.base import RGBDDataset, RGBDFrame
from server.datasets.record3d import R3D_SUFFIX, Record3DDataset
from server.datasets.redwood import RedwoodDataset
from server.datasets.stray import StrayDataset, is_stray_folder
from server.datasets.tum import TUMDataset
from server.errors import DatasetError

# Format name -> loader class; each takes the path (a folder, or the .r3d file) plus its own
# keyword arguments, so their constructors differ beyond the path.
DATASETS: dict[str, Callable[..., RGBDDataset]] = {
    "tum": TUMDataset,
    "redwood": RedwoodDataset,
    "stray": StrayDataset,
    "record3d": Record3DDataset,
}


def sniff_format(path: Path) -> str | None:
    """The format name a path's layout suggests, or None when it matches none."""
    if path.is_file():
        return "record3d" if path.suffix.lower() == R3D_SUFFIX else None
    # Before Redwood: a Stray export has depth/ too (but no color/ or image/).
    if is_stray_folder(path):
        return "stray"
    if (path / "rgb.txt").is_file():
        return "tum"
    if ((path / "color").is_dir() or (path / "image").is_dir()) and (path / "depth").is_dir():
        return "redwood"
    return None


def open_dataset(path: str | Path, fmt: str | None = None, **kwargs) -> RGBDDataset:
    """Open the RGB-D sequence in ``path`` with the loader named ``fmt``, or the one its layout
    suggests; ``kwargs`` go to the loader (e.g. ``intrinsics``). Raises DatasetError otherwise."""
    path = Path(path)
    known = ", ".join(sorted(DATASETS))
    if fmt is None:
        if not path.exists():
            raise DatasetError(f"dataset {path} does not exist")
        fmt = sniff_format(path)
        if fmt is None:
            raise DatasetError(
                f"cannot tell the format of {path} (tum: rgb.txt; redwood: color/ or image/ and "
                f"depth/; stray: rgb.mp4, depth/ and odometry.csv; record3d: a .r3d file); "
                f"pass one of: {known}"
            )
    loader = DATASETS.get(fmt.lower())
    if loader is None:
        raise DatasetError(f"unknown dataset format {fmt!r}; known formats: {known}")
    return loader(path, **kwargs)


__all__ = [
    "DATASETS",
    "RGBDDataset",
    "RGBDFrame",
    "Record3DDataset",
    "RedwoodDataset",
    "StrayDataset",
    "TUMDataset",
    "open_dataset",
    "sniff_format",
]
