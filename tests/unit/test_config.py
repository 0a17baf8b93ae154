"""The one configuration: sections, sources and their order, validation, the core's sections."""

from __future__ import annotations

import dataclasses
import json
import pickle

import pytest
from pydantic import ValidationError

from server.config import (
    FLAT_ENV,
    Config,
    ServerConfig,
    load_config,
    parse_overrides,
    write_config,
)
from server.errors import ConfigError
from server.geometry import Intrinsics
from server.mapping.config import MAX_PREVIEW_POINTS, MappingConfig, TSDFConfig
from server.registration.config import RegistrationConfig
from server.sessions.config import SessionConfig
from server.simulation.config import SimulationConfig
from tests.support.paths import REPO


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch):
    """No DRONESIM_* variable of the machine running the tests leaks into these."""
    import os

    for name in list(os.environ):
        if name.upper().startswith("DRONESIM_"):
            monkeypatch.delenv(name)


# ---- the core's sections ------------------------------------------------------------------------


def test_overrides_change_one_field_and_keep_the_rest():
    cfg = RegistrationConfig().with_overrides(solver={"dense": False})
    assert cfg.solver.dense is False
    assert cfg.solver.max_iterations == RegistrationConfig().solver.max_iterations


@pytest.mark.parametrize("sections", [{"nosuch": {}}, {"solver": {"nosuch": 1}}])
def test_unknown_settings_are_refused(sections):
    with pytest.raises(ConfigError):
        RegistrationConfig().with_overrides(**sections)


def test_inconsistent_thresholds_are_refused():
    with pytest.raises(ConfigError):
        RegistrationConfig().with_overrides(state={"lost_inliers": 100, "ok_inliers": 50})


@pytest.mark.parametrize("fx", [0.0, -1.0, float("nan")])
def test_absurd_intrinsics_are_refused(fx):
    with pytest.raises(ConfigError):
        Intrinsics(fx, 500.0, 320.0, 240.0, 640, 480)


def test_the_sections_are_the_objects_the_core_takes_with_their_own_defaults():
    config = load_config()
    assert config.registration == RegistrationConfig()
    assert config.simulation == SimulationConfig()
    assert config.mapping == MappingConfig() and config.mapping.tsdf == TSDFConfig()
    assert type(config.registration) is RegistrationConfig  # a plain dataclass, not a copy
    # dataclasses.replace still works on what the configuration holds
    faster = dataclasses.replace(config.registration.solver, dense=False)
    assert (
        faster.dense is False and faster.max_iterations == config.registration.solver.max_iterations
    )


# ---- sources and their order --------------------------------------------------------------------


def test_file_then_environment_then_set_then_flags(tmp_path, monkeypatch):
    file = tmp_path / "c.yaml"
    file.write_text(
        "registration:\n  keyframes:\n    max_rotation_deg: 11\n    min_tracked: 70\n"
        "server:\n  port: 9001\n  host: 0.0.0.0\n  max_sessions: 3\n"
    )
    monkeypatch.setenv("DRONESIM_REGISTRATION__KEYFRAMES__MIN_TRACKED", "60")
    monkeypatch.setenv("DRONESIM_PORT", "9002")  # flat, as documented
    monkeypatch.setenv("DRONESIM_SERVER__MAX_SESSIONS", "4")  # nested
    monkeypatch.setenv("DRONESIM_MAX_SESSIONS", "5")  # flat: the nested one wins
    config = load_config(
        file,
        ["registration.solver.dense=false", "server.port=9003"],
        {"server": {"port": 9004}},
    )
    assert config.registration.keyframes.max_rotation_deg == 11.0  # file
    assert config.registration.keyframes.min_tracked == 60  # environment over file
    assert config.registration.solver.dense is False  # --set
    assert config.server.host == "0.0.0.0"  # file, untouched by the rest
    assert config.server.max_sessions == 4
    assert config.server.port == 9004  # flags over --set over environment over file
    assert load_config(file, ["server.port=9003"]).server.port == 9003
    assert load_config(file).server.port == 9002
    monkeypatch.delenv("DRONESIM_PORT")
    assert load_config(file).server.port == 9001


def test_a_toml_file_reads_like_a_yaml_one(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text("[registration.solver]\ndense = false\n\n[mapping]\nfuse_every = 5\n")
    config = load_config(toml)
    assert config.registration.solver.dense is False and config.mapping.fuse_every == 5


def test_the_documented_flat_variables_still_work(monkeypatch, tmp_path):
    monkeypatch.setenv("DRONESIM_HOST", "0.0.0.0")
    monkeypatch.setenv("DRONESIM_DATA_DIR", str(tmp_path / "d"))
    monkeypatch.setenv("DRONESIM_TLS", "true")
    monkeypatch.setenv("DRONESIM_VOXEL_M", "0.03")
    monkeypatch.setenv("DRONESIM_FUSE_EVERY", "2")
    monkeypatch.setenv("DRONESIM_PREVIEW_POINTS", "5000")
    monkeypatch.setenv("DRONESIM_CORS_ORIGINS", '["https://a.example"]')
    monkeypatch.setenv("DRONESIM_CACHE", str(tmp_path))  # the demo's cache: not a config key
    for config in (load_config(), Config()):
        assert config.server.host == "0.0.0.0" and config.server.tls is True
        assert config.server.data_dir == tmp_path / "d"
        assert config.mapping.tsdf.voxel_m == 0.03
        assert config.mapping.fuse_every == 2 and config.mapping.preview_points == 5000
        assert config.server.cors_origins == ["https://a.example"]


def test_every_flat_name_leads_to_a_key():
    defaults = Config.defaults().to_dict()
    for name, path in FLAT_ENV.items():
        node = defaults
        for part in path:
            node = node[part]
        assert path[-1] == name
    assert set(ServerConfig.model_fields) <= set(FLAT_ENV)


def test_defaults_ignore_the_environment(monkeypatch):
    monkeypatch.setenv("DRONESIM_PORT", "9100")
    monkeypatch.setenv("DRONESIM_REGISTRATION__SOLVER__DENSE", "true")
    assert Config.defaults().server.port == 8000
    assert SessionConfig.from_config().registration.solver.dense is False
    assert load_config().registration.solver.dense is True


def test_set_values_are_read_as_yaml():
    values = parse_overrides(
        ["a.b=10", "a.c=false", "a.d=[1, 2, 3]", "e=0.0.0.0", "f.g=some text", "f.h="]
    )
    assert values == {
        "a": {"b": 10, "c": False, "d": [1, 2, 3]},
        "e": "0.0.0.0",
        "f": {"g": "some text", "h": ""},
    }


def test_a_written_configuration_reads_back_equal(tmp_path):
    config = load_config(
        overrides=[
            "registration.keyframes.max_rotation_deg=9.5",
            "simulation.inertia_kg_m2=[0.003, 0.003, 0.005]",
            "mapping.tsdf.carve_free_space=false",
            f"server.data_dir={tmp_path / 'd'}",
            "server.ray=auto",
        ]
    )
    path = write_config(config, tmp_path / "out" / "config.yaml")
    again = load_config(path)
    assert again == config
    assert again.simulation.inertia_kg_m2 == (0.003, 0.003, 0.005)
    assert config != Config.defaults()


# ---- validation ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "override, named",
    [
        ("registration.keyframes.nosuch=1", "registration.keyframes.nosuch: unknown key"),
        ("nosuch.key=1", "nosuch: unknown key"),
        ("server.port=70000", "server.port"),
        ("server.port=many", "server.port"),
        ("registration.solver.dense_stride=0", "registration.solver.dense_stride"),
        ("registration.state.lost_inliers=100", "registration.state.lost_inliers"),
        ("simulation.physics_hz=100", "simulation.physics_hz"),
        ("mapping.tsdf.voxel_m=-1", "mapping"),
        ("server.cors_origins=['*']", "server.cors_origins"),
        ("server.allocator=tcmalloc", "server.allocator"),
    ],
)
def test_a_bad_value_or_unknown_key_is_refused_naming_the_key(override, named):
    with pytest.raises(ConfigError) as info:
        load_config(overrides=[override])
    assert named in str(info.value)


def test_unknown_keys_in_a_file_and_the_environment_are_refused(tmp_path, monkeypatch):
    file = tmp_path / "c.yaml"
    file.write_text("mapping:\n  fuse_evry: 2\n")
    with pytest.raises(ConfigError, match="mapping.fuse_evry: unknown key"):
        load_config(file)
    monkeypatch.setenv("DRONESIM_REGISTRATION__SOLVER__DENSER", "true")
    with pytest.raises(ConfigError, match="registration.solver.denser: unknown key"):
        load_config()


@pytest.mark.parametrize(
    "text, message",
    [("[1, 2]\n", "mapping of sections"), ("a: [\n", "not valid yaml")],
)
def test_a_malformed_file_is_refused(tmp_path, text, message):
    file = tmp_path / "c.yaml"
    file.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(file)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        load_config(overrides=["server.port"])


def test_preview_points_are_bounded_by_what_the_protocol_allows_in_one_chunk():
    limits = json.loads((REPO / "shared" / "protocol.json").read_text())["limits"]
    assert MAX_PREVIEW_POINTS == limits["max_map_chunk_points"]
    assert load_config(overrides=[f"mapping.preview_points={MAX_PREVIEW_POINTS}"])
    with pytest.raises(ConfigError, match="mapping.preview_points"):
        load_config(overrides=[f"mapping.preview_points={MAX_PREVIEW_POINTS + 1}"])
    with pytest.raises(ConfigError, match="mapping.preview_points"):
        MappingConfig(preview_points=100_000)


def test_a_bad_flat_variable_stops_config_construction(monkeypatch):
    monkeypatch.setenv("DRONESIM_PREVIEW_POINTS", "20000")
    with pytest.raises(ValidationError, match="preview_points"):
        Config()
    with pytest.raises(ConfigError, match="mapping.preview_points"):
        load_config()


# ---- what a session gets ------------------------------------------------------------------------


def test_a_session_gets_the_configurations_sections_and_they_pickle():
    config = load_config(
        overrides=[
            "registration.keyframes.max_rotation_deg=10",
            "mapping.fuse_every=4",
            "simulation.max_speed_m_s=2.0",
            "server.snapshot_interval_s=5",
            "server.drone_state_hz=10",
        ]
    )
    session = SessionConfig.from_config(config)
    assert session.registration is config.registration
    assert session.mapping.fuse_every == 4
    assert session.simulation.max_speed_m_s == 2.0
    assert session.snapshot_interval_s == 5.0 and session.drone_state_hz == 10.0
    copy = pickle.loads(pickle.dumps(session))  # crosses to a worker process or a Ray actor
    assert copy == session
    assert SessionConfig.from_config() == SessionConfig.from_config(Config.defaults())


# ---- the docs -----------------------------------------------------------------------------------


def test_the_docs_document_every_flat_variable_and_their_examples_load(tmp_path):
    doc = (REPO / "docs" / "CONFIGURATION.md").read_text()
    for name in FLAT_ENV:
        assert f"`{name.upper()}`" in doc, f"DRONESIM_{name.upper()} is not in CONFIGURATION.md"
    section = doc[doc.index("## Sections, files, variables, flags") :]
    for suffix in ("yaml", "toml"):
        block = section.split(f"```{suffix}\n", 1)[1].split("```", 1)[0]
        path = tmp_path / f"example.{suffix}"
        path.write_text(block)
        config = load_config(path)
        assert config.registration.keyframes.max_rotation_deg == 10.0
        assert config.server.port == 8080
