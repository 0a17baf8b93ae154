"""The offline commands: ``track`` registers a sequence, ``evaluate`` scores a trajectory."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from server.cli.common import (
    ConfigFile,
    ConfigSets,
    console,
    effective_config,
    open_sequence,
    print_config,
)
from server.errors import DroneSimError


def track(
    dataset: Annotated[
        str,
        typer.Argument(
            help="sequence: a TUM or Redwood folder, a Stray Scanner export folder, a Record3D "
            ".r3d file, or 'demo'"
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(
            help="folder of the runs: each run writes a new folder OUT/DATASET_DATE_TIME and "
            "OUT/latest links to the newest"
        ),
    ] = Path("results/track"),
    frames: Annotated[int | None, typer.Option(help="only N frames (from --start)")] = None,
    start: Annotated[int, typer.Option(min=0, help="begin at this frame (0 = the first)")] = 0,
    dense: Annotated[
        bool | None,
        typer.Option(
            "--dense/--no-dense",
            help="dense point-to-plane refinement (registration.solver.dense; default: on)",
        ),
    ] = None,
    device_prior: Annotated[
        bool | None,
        typer.Option(
            "--device-prior/--no-device-prior",
            help="an iPhone recording's own odometry as the tracker's prior "
            "(registration.prior.enabled; default: on)",
        ),
    ] = None,
    room: Annotated[
        Path | None,
        typer.Option(
            help="continue in the room saved by an earlier run (its run folder or the room "
            "folder in it; an --out folder means its latest run): relocalise by place "
            "recognition, track in its frame, extend it",
        ),
    ] = None,
    save_room: Annotated[
        bool,
        typer.Option(
            "--save-room/--no-save-room",
            help="keep the keyframes and save RUN/room (ORB features per keyframe, a TSDF "
            "fused from them behind tracking)",
        ),
    ] = True,
    mesh: Annotated[
        bool,
        typer.Option(
            "--mesh/--no-mesh",
            help="also write the keyframes' TSDF surface upright: RUN/mesh.ply (z up) and "
            "RUN/mesh.glb (y up, as glTF defines); up from the phone's gravity, else the map's "
            "floors and table tops, else the first camera",
        ),
    ] = False,
    overlap: Annotated[
        bool,
        typer.Option(
            "--overlap/--no-overlap",
            help="read frames ahead of the tracker and map behind it on threads of their own "
            "(same results; --no-overlap runs the stages in turn)",
        ),
    ] = True,
    fx: Annotated[
        float | None,
        typer.Option(help="focal length x, px (with --fy --cx --cy: overrides the dataset's)"),
    ] = None,
    fy: Annotated[float | None, typer.Option(help="focal length y, px")] = None,
    cx: Annotated[float | None, typer.Option(help="principal point x, px")] = None,
    cy: Annotated[float | None, typer.Option(help="principal point y, px")] = None,
    depth_scale: Annotated[float | None, typer.Option(help="depth units per metre")] = None,
    config_file: ConfigFile = None,
    sets: ConfigSets = None,
) -> None:
    """Register a sequence; write trajectory (TUM), map (PLY), a top-view picture, metrics, the
    configuration used (config.yaml: `--config RUN/config.yaml` runs it again), the room
    (RUN/room: keyframes and TSDF map, for a later --room) and with --mesh an upright mesh.
    RUN is a new folder under --out for each run; OUT/latest links to the newest. A Stray
    Scanner or Record3D recording's own odometry is each frame's prior unless
    --no-device-prior."""
    from server.config import write_config
    from server.evaluation.metrics import format_table
    from server.pipeline import run_odometry, write_outputs
    from server.results import link_latest, new_run_folder, room_folder

    registration: dict = {}
    if dense is not None:
        registration["solver"] = {"dense": dense}
    if device_prior is not None:
        registration["prior"] = {"enabled": device_prior}
    flags = {"registration": registration} if registration else {}
    config = effective_config(config_file, sets, flags)
    ds = open_sequence(dataset, fx, fy, cx, cy, depth_scale)
    saved_room = None
    if room is not None:
        from server.rooms import load_room

        saved_room = load_room(room_folder(room), config.registration)
    print_config(config, "configuration")
    run = run_odometry(
        ds,
        config.registration,
        max_frames=frames,
        mapping=config.mapping,
        room=saved_room,
        start=start,
        keep_room=save_room or mesh,  # the mesh is fused from the keyframes
        overlap=overlap,
    )
    if saved_room is not None and not run.summary["relocalisation"]["relocalised"]:
        raise DroneSimError(
            f"no frame of {ds.name} was recognised in the room {room}: nothing tracked"
        )
    folder = new_run_folder(out, ds.name)
    paths = write_outputs(run, folder, ds, config.registration, mesh=mesh, save_room=save_room)
    paths["config"] = write_config(config, folder / "config.yaml")
    latest = link_latest(folder)
    s = run.summary
    stats = Table(title=f"{ds.name}: registration")
    for col in ("frames", "keyframes", "ok", "weak", "lost", "repeated", "median ms", "p90 ms"):
        stats.add_column(col, justify="right")
    st = s["states"]
    stats.add_row(
        str(s["frames"]),
        str(s["keyframes"]),
        str(st.get("ok", 0)),
        str(st.get("weak", 0)),
        str(st.get("lost", 0)),
        str(sum(s.get("repeated", {}).values())),
        f"{s['median_ms']:.1f}",
        f"{s['p90_ms']:.1f}",
    )
    console.print(stats)
    prior = s["device_prior"]
    if prior["frames"]:
        console.print(
            f"device prior: {prior['frames']} frames carried the recording's odometry, "
            f"{prior['guesses']} started from it"
        )
    elif ds.device_poses is not None:
        console.print("device prior: off (the recording's odometry was not used)")
    found = s.get("relocalisation")
    if found is not None:
        console.print(
            f"relocalised in the room at frame {found['sequence_frame']} "
            f"(keyframe {found['keyframe']}, {found['inliers']} inliers, {found['ms']:.0f} ms; "
            f"{found['total_ms']:.0f} ms in all)"
        )
    if run.metrics is not None:
        console.print(
            format_table({"estimate": run.metrics}, title=f"{ds.name}: error vs ground truth")
        )
    upright = s.get("upright")
    if upright is not None:
        said = {"gravity": "the phone's gravity", "surfaces": "the map's floors and table tops"}
        console.print(f"mesh: up from {said.get(upright['source'], 'the first camera (-y)')}")
    for name, path in paths.items():
        console.print(f"{name:>10}: {path}")
    if latest is not None:
        console.print(f"{'latest':>10}: {latest} -> {folder.name}")


def evaluate_cmd(
    groundtruth: Annotated[Path, typer.Argument(help="ground truth, TUM format")],
    estimate: Annotated[Path, typer.Argument(help="estimate, TUM format")],
    max_diff: Annotated[float, typer.Option(help="timestamp tolerance, seconds")] = 0.02,
    align: Annotated[
        str,
        typer.Option(
            help="how the estimate is aligned to the ground truth before the ATE: se3 (rigid), "
            "sim3 (with scale) or none"
        ),
    ] = "se3",
    delta: Annotated[float, typer.Option(help="the second RPE's step, in --delta-unit")] = 1.0,
    delta_unit: Annotated[
        str, typer.Option(help="what --delta counts: seconds or frames")
    ] = "seconds",
    json_out: Annotated[
        Path | None,
        typer.Option("--json", metavar="FILE", help="also write the metrics as JSON (metres, deg)"),
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option(
            metavar="FILE", help="also write a top view (PNG) of both, the estimate aligned"
        ),
    ] = None,
) -> None:
    """Print ATE and RPE of an estimated trajectory against ground truth (RPE per frame and
    over --delta); optionally write them as JSON and the two trajectories as a picture."""
    import json

    from server.evaluation.metrics import (
        ALIGNMENTS,
        DeltaUnit,
        aligned,
        associate_trajectories,
        evaluate,
        format_table,
    )
    from server.evaluation.trajectory import read_tum

    if align not in ALIGNMENTS:
        raise DroneSimError(f"--align must be one of {', '.join(ALIGNMENTS)}, not {align!r}")
    if delta_unit not in [u.value for u in DeltaUnit]:
        raise DroneSimError(f"--delta-unit must be seconds or frames, not {delta_unit!r}")
    gt, est = read_tum(groundtruth), read_tum(estimate)
    metrics = evaluate(gt, est, max_diff=max_diff, align=align, delta=delta, delta_unit=delta_unit)
    console.print(format_table({estimate.name: metrics}))
    if json_out is not None:
        report = {
            "groundtruth": str(groundtruth),
            "estimate": str(estimate),
            "align": align,
            "rpe_delta": {"value": delta, "unit": delta_unit},
            **metrics,
        }
        json_out.write_text(json.dumps(report, indent=2) + "\n")
    if plot is not None:
        from server.evaluation.plots import plot_top_view

        gt_m, est_m = associate_trajectories(gt, est, max_diff)  # as evaluate() paired them
        curves = {
            "ground truth": gt_m.poses,
            f"{estimate.stem} ({align})": aligned(gt_m, est_m, align).poses,
        }
        plot_top_view(plot, curves, title=f"{estimate.name} against {groundtruth.name}")
