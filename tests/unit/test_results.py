"""track's results folders: a new folder per run, the ``latest`` link, and finding a run's room."""

from __future__ import annotations

import pytest

from server.results import (
    ResultsError,
    link_latest,
    new_run_folder,
    room_folder,
    run_folder_name,
)

NOON = 1_700_000_000.0  # a fixed time: the names below must not depend on when tests run


def test_each_run_gets_a_new_folder_even_within_one_second(tmp_path):
    first = new_run_folder(tmp_path / "out", "tum fr1/xyz", NOON)
    second = new_run_folder(tmp_path / "out", "tum fr1/xyz", NOON)
    assert first.name == run_folder_name("tum fr1/xyz", NOON)
    assert first.name.startswith("tum-fr1-xyz_20")  # safe characters only
    assert second.name == f"{first.name}_2"
    assert first.is_dir() and second.is_dir() and not any(first.iterdir())


def test_latest_follows_the_newest_run_and_is_relative(tmp_path):
    first = new_run_folder(tmp_path, "a", NOON)
    assert link_latest(first) == tmp_path / "latest"
    second = new_run_folder(tmp_path, "b", NOON)
    (second / "trajectory.tum").write_text("# t\n")
    link_latest(second)
    latest = tmp_path / "latest"
    assert latest.is_symlink() and latest.readlink().name == second.name
    assert not latest.readlink().is_absolute()  # the folder can move as a whole
    assert (latest / "trajectory.tum").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["latest", first.name, second.name])


def test_a_folder_called_latest_is_not_replaced(tmp_path):
    (tmp_path / "latest").mkdir()
    with pytest.raises(ResultsError, match="not a link"):
        link_latest(new_run_folder(tmp_path, "a", NOON))


def test_a_runs_own_folder_is_not_taken_as_out(tmp_path):
    run = new_run_folder(tmp_path, "a", NOON)
    (run / "summary.json").write_text("{}")
    with pytest.raises(ResultsError, match="a run's folder"):
        new_run_folder(run, "b", NOON)
    with pytest.raises(ResultsError, match="a run's folder"):
        new_run_folder(tmp_path / "latest", "b", NOON)


def test_the_room_is_found_from_its_folder_its_run_or_the_runs_latest(tmp_path):
    run = new_run_folder(tmp_path, "a", NOON)
    (run / "room").mkdir()
    (run / "room" / "room.json").write_text("{}")
    link_latest(run)
    for given in (run / "room", run, tmp_path / "latest", tmp_path):
        assert room_folder(given).resolve() == (run / "room").resolve(), given
    with pytest.raises(ResultsError, match="no room at"):
        room_folder(tmp_path / "nowhere")
