"""What every command shares: the consoles, the configuration options and how they are read,
and how a dataset argument is opened."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from server.errors import DroneSimError

console = Console()
err_console = Console(stderr=True, soft_wrap=True)

# Every command that runs the pipeline or the server takes the configuration the same way.
ConfigFile = Annotated[
    Path | None,
    typer.Option(
        "--config",
        metavar="FILE",
        help="configuration file (YAML or TOML; `python -m server config` prints one)",
    ),
]
ConfigSets = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        metavar="KEY=VALUE",
        help="override one key, e.g. registration.keyframes.max_rotation_deg=10 (repeatable)",
    ),
]


def effective_config(config_file: Path | None, sets: list[str] | None, flags: dict | None = None):
    """The effective configuration (defaults < file < DRONESIM_* environment < --set < flags);
    a bad value stops the command here with a ConfigError naming the key."""
    from server.config import load_config

    return load_config(config_file, sets or (), flags)


def print_config(config, title: str) -> None:
    console.rule(title)
    console.print(config.to_yaml().rstrip(), markup=False, highlight=False)
    console.rule()


def open_sequence(dataset: str, fx, fy, cx, cy, depth_scale):
    """Open a sequence folder, or the bundled demo sequence for the name 'demo'."""
    from server.datasets import open_dataset

    if dataset == "demo":
        from server.datasets.demo import demo_sequence_path

        return open_dataset(demo_sequence_path(), "tum")
    kwargs = {}
    if fx is not None:
        if None in (fy, cx, cy):
            raise DroneSimError("--fx needs --fy, --cx and --cy too")
        kwargs["intrinsics"] = _intrinsics_for(Path(dataset), fx, fy, cx, cy)
    if depth_scale is not None:
        kwargs["depth_scale"] = depth_scale
    return open_dataset(dataset, **kwargs)


def _intrinsics_for(path: Path, fx: float, fy: float, cx: float, cy: float):
    """Intrinsics from the command line; the image size is read off the first image."""
    import cv2

    from server.geometry import Intrinsics

    images = sorted(p for p in path.rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not images:
        raise DroneSimError(f"no images under {path}")
    first = cv2.imread(str(images[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise DroneSimError(f"cannot read the image {images[0]}")
    h, w = first.shape[:2]
    return Intrinsics(fx, fy, cx, cy, w, h)
