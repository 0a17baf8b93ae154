"""TUM and Redwood loaders on small slices of the shared sequences, plus format sniffing.

The slices live in tmp_path: list files are rewritten, image folders are symlinked to the data.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from server.datasets import RedwoodDataset, TUMDataset, open_dataset
from server.datasets.redwood import PRIMESENSE_DEFAULT
from server.datasets.tum import TUM_DEFAULT_INTRINSICS
from server.errors import DatasetError
from server.evaluation.trajectory import associate
from tests.support.paths import SHARED_DATA

DATA = SHARED_DATA
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared data not found at {DATA}")

SEQUENCES = [("7scenes_a", 1000.0, 585.0), ("synthetic_room0", 5000.0, 525.0)]


def head(path: Path, n: int) -> list[str]:
    """The first ``n`` data rows (no comments) of a TUM list file."""
    rows = [line for line in path.read_text().splitlines() if line and not line.startswith("#")]
    return rows[:n]


def shift(rows: list[str], offset_s: float) -> list[str]:
    return [f"{float(r.split()[0]) + offset_s:.6f} {' '.join(r.split()[1:])}" for r in rows]


def make_tum_slice(
    src: Path, dst: Path, n: int = 5, depth_offset_s: float = 0.0, with_json: bool = True
) -> Path:
    """A TUM folder listing the first ``n`` frames of ``src``; images are symlinks into ``src``."""
    dst.mkdir(parents=True)
    for folder in ("rgb", "depth"):
        (dst / folder).symlink_to(src / folder, target_is_directory=True)
    (dst / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(head(src / "rgb.txt", n)))
    depth_rows = shift(head(src / "depth.txt", n), depth_offset_s)
    (dst / "depth.txt").write_text("# timestamp filename\n" + "\n".join(depth_rows))
    (dst / "groundtruth.txt").write_text("\n".join(head(src / "groundtruth.txt", n)))
    if with_json:
        (dst / "intrinsics.json").symlink_to(src / "intrinsics.json")
    return dst


def make_redwood(src: Path, dst: Path, n: int = 3, n_depth: int | None = None) -> Path:
    """A Redwood folder (color/, depth/) with the first frames of ``src`` symlinked in."""
    (dst / "color").mkdir(parents=True)
    (dst / "depth").mkdir()
    for row in head(src / "rgb.txt", n):
        name = row.split()[1]
        (dst / "color" / Path(name).name).symlink_to(src / name)
    for row in head(src / "depth.txt", n if n_depth is None else n_depth):
        name = row.split()[1]
        (dst / "depth" / Path(name).name).symlink_to(src / name)
    return dst


@pytest.mark.parametrize(("sequence", "scale", "fx"), SEQUENCES)
def test_tum_loads_frames_with_metric_depth(tmp_path, sequence, scale, fx):
    folder = make_tum_slice(DATA / sequence, tmp_path / sequence)
    ds = TUMDataset(folder)
    assert len(ds) == 5
    assert ds.depth_scale == scale
    assert ds.intrinsics.fx == fx and (ds.intrinsics.width, ds.intrinsics.height) == (640, 480)
    assert ds.ground_truth is not None and len(ds.ground_truth) == 5
    np.testing.assert_allclose(ds.timestamps, ds.ground_truth.timestamps)
    frame = ds[4]
    assert frame.index == 4 and frame.timestamp == ds.timestamps[4]
    assert frame.colour.shape == (480, 640, 3) and frame.colour.dtype == np.uint8
    assert frame.depth.shape == (480, 640) and frame.depth.dtype == np.float32
    valid = frame.depth[frame.depth > 0]
    assert valid.size > 0.5 * frame.depth.size
    assert 0.1 < valid.min() and valid.max() < 10.0  # metres, not millimetres
    depth_file = head(DATA / sequence / "depth.txt", 5)[4].split()[1]
    raw = cv2.imread(str(DATA / sequence / depth_file), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(frame.depth, raw / scale, rtol=1e-6)


def test_tum_colour_is_rgb_order(tmp_path):
    folder = make_tum_slice(DATA / "synthetic_room0", tmp_path / "seq", n=1)
    frame = TUMDataset(folder)[0]
    bgr = cv2.imread(str(folder / head(folder / "rgb.txt", 1)[0].split()[1]))
    np.testing.assert_array_equal(frame.colour, bgr[:, :, ::-1])


def test_tum_associates_depth_within_tolerance(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq", depth_offset_s=0.01)
    ds = TUMDataset(folder, max_time_diff=0.02)
    assert len(ds) == 5
    np.testing.assert_allclose(ds.timestamps, ds.ground_truth.timestamps)  # the rgb stamps
    raw = cv2.imread(str(folder / "depth" / "000002.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(ds[2].depth, raw / 1000.0, rtol=1e-6)


def test_no_matches_due_to_offset(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq", depth_offset_s=0.5)
    with pytest.raises(DatasetError, match="max_time_diff=0.02"):
        TUMDataset(folder, max_time_diff=0.02)


def test_associate_is_one_to_one_and_greedy_by_smallest_difference():
    idx_a, idx_b = associate(np.array([0.0, 0.1, 0.2]), np.array([0.09, 0.105, 0.5]), 0.02)
    # 0.1 matches both 0.09 and 0.105; the closer one wins and 0.09 stays unmatched.
    assert idx_a.tolist() == [1] and idx_b.tolist() == [1]
    idx_a, idx_b = associate(np.array([0.0, 1.0]), np.array([5.0]), 0.02)
    assert len(idx_a) == len(idx_b) == 0


def test_bad_row_names_file_and_line(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq")
    rows = (folder / "depth.txt").read_text().splitlines()
    rows.insert(2, "not-a-time depth/000001.png")
    (folder / "depth.txt").write_text("\n".join(rows))
    with pytest.raises(DatasetError, match=r"depth\.txt:3"):
        TUMDataset(folder)


def test_bad_groundtruth_row_is_dataset_error(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq")
    (folder / "groundtruth.txt").write_text("1.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:1"):
        TUMDataset(folder)


def test_missing_list_file_raises(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq")
    (folder / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth\.txt"):
        TUMDataset(folder)


def test_missing_image_raises_on_access(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq")
    rows = (folder / "rgb.txt").read_text().splitlines()
    (folder / "rgb.txt").write_text("\n".join([*rows[:-1], rows[-1].replace("rgb/", "nope/")]))
    ds = TUMDataset(folder)
    ds[0]
    with pytest.raises(DatasetError, match="cannot read colour image"):
        ds[4]


def test_image_size_contradicting_intrinsics_raises(tmp_path):
    folder = make_tum_slice(DATA / "7scenes_a", tmp_path / "seq", with_json=False)
    K = {"fx": 585.0, "fy": 585.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240}
    (folder / "intrinsics.json").write_text(json.dumps(K))
    with pytest.raises(DatasetError, match="640x480 but the intrinsics say 320x240"):
        TUMDataset(folder)[0]


def test_tum_defaults_by_folder_name(tmp_path):
    folder = make_tum_slice(
        DATA / "synthetic_room0", tmp_path / "rgbd_dataset_freiburg2_xyz", with_json=False
    )
    ds = TUMDataset(folder)
    assert ds.intrinsics == TUM_DEFAULT_INTRINSICS["fr2"] and ds.depth_scale == 5000.0


def test_tum_without_intrinsics_says_which_flags_to_pass(tmp_path):
    folder = make_tum_slice(DATA / "synthetic_room0", tmp_path / "seq", with_json=False)
    with pytest.raises(DatasetError, match="--fx"):
        TUMDataset(folder)
    explicit = TUM_DEFAULT_INTRINSICS["fr3"]
    assert TUMDataset(folder, intrinsics=explicit, depth_scale=5000.0).intrinsics == explicit


def test_redwood_loads_frames_with_open3d_intrinsics(tmp_path):
    o3d = pytest.importorskip("open3d")
    folder = make_redwood(DATA / "7scenes_a", tmp_path / "redwood")
    K = o3d.camera.PinholeCameraIntrinsic(640, 480, 585.0, 586.0, 320.0, 241.0)
    o3d.io.write_pinhole_camera_intrinsic(str(folder / "camera_intrinsic.json"), K)
    ds = RedwoodDataset(folder)
    assert len(ds) == 3 and ds.depth_scale == 1000.0 and ds.ground_truth is None
    i = ds.intrinsics
    assert (i.fx, i.fy, i.cx, i.cy, i.width, i.height) == (585.0, 586.0, 320.0, 241.0, 640, 480)
    np.testing.assert_allclose(ds.timestamps, np.arange(3) / 30.0)
    frame = ds[2]
    assert frame.colour.shape == (480, 640, 3) and frame.colour.dtype == np.uint8
    raw = cv2.imread(str(DATA / "7scenes_a" / "depth" / "000002.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(frame.depth, raw / 1000.0, rtol=1e-6)
    assert 0.1 < frame.depth[frame.depth > 0].min() and frame.depth.max() < 10.0


def test_redwood_defaults_and_ground_truth(tmp_path):
    folder = make_redwood(DATA / "7scenes_a", tmp_path / "redwood")
    (folder / "groundtruth.txt").write_text("\n".join(head(DATA / "7scenes_a/groundtruth.txt", 3)))
    ds = RedwoodDataset(folder)
    assert ds.intrinsics == PRIMESENSE_DEFAULT
    assert ds.ground_truth is not None and len(ds.ground_truth) == 3


def test_redwood_count_mismatch_raises(tmp_path):
    folder = make_redwood(DATA / "7scenes_a", tmp_path / "redwood", n=3, n_depth=2)
    with pytest.raises(DatasetError, match="3 colour images"):
        RedwoodDataset(folder)


def test_open_dataset_sniffs_the_format(tmp_path):
    tum = make_tum_slice(DATA / "7scenes_a", tmp_path / "tum")
    redwood = make_redwood(DATA / "7scenes_a", tmp_path / "redwood")
    assert isinstance(open_dataset(tum), TUMDataset)
    assert isinstance(open_dataset(redwood), RedwoodDataset)
    assert isinstance(open_dataset(tum, fmt="tum", max_time_diff=0.01), TUMDataset)
    with pytest.raises(DatasetError, match="record3d, redwood, stray, tum"):
        open_dataset(tmp_path)
    with pytest.raises(DatasetError, match="unknown dataset format 'kitti'"):
        open_dataset(tum, fmt="kitti")
