"""Docker does not run here: check that the deployment files say what the docs (README.md and
docs/) say."""

from __future__ import annotations

import re

import yaml

from server.config import FLAT_ENV
from tests.support.paths import REPO


def _docs() -> str:
    """What the README and the documents under docs/ say, as one text."""
    paths = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    return "\n".join(p.read_text() for p in paths)


def test_compose_names_the_service_port_volume_and_health_check():
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    server = compose["services"]["server"]
    assert server["build"] == "."
    assert "8000:8000" in server["ports"]
    volume, mount = server["volumes"][0].split(":")
    assert mount == server["environment"]["DRONESIM_DATA_DIR"] == "/data"
    assert volume in compose["volumes"]
    health = " ".join(server["healthcheck"]["test"])
    assert "/healthz" in health and "8000" in health
    # Every DRONESIM_ variable the file sets is a real setting.
    fields = {f"DRONESIM_{name.upper()}" for name in FLAT_ENV}
    assert set(server["environment"]) <= fields


def test_compose_loadtest_profile_replays_the_demo_against_the_server_as_the_readme_says():
    import typer

    from server.cli import app

    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    loadtest = compose["services"]["loadtest"]
    assert loadtest["profiles"] == ["loadtest"]  # not started by a plain `docker compose up`
    assert loadtest["image"] == compose["services"]["server"]["image"]
    assert loadtest["depends_on"]["server"]["condition"] == "service_healthy"
    command = loadtest["command"]
    assert command[:5] == ["python", "-m", "server", "loadtest", "demo"]
    assert command[command.index("--url") + 1] == "http://server:8000"  # the service's port
    # Every option it passes is one the CLI knows, and the report lands on the mounted folder.
    options = {o for p in typer.main.get_command(app).commands["loadtest"].params for o in p.opts}
    assert {arg for arg in command if arg.startswith("--")} <= options
    mount = loadtest["volumes"][0].split(":")[1]
    assert command[command.index("--json") + 1].startswith(mount + "/")
    docs = _docs()
    assert "docker compose --profile loadtest run --rm loadtest" in docs
    assert "python3 benchmarks/capacity.py" in docs


def test_dockerfile_installs_the_package_and_serves_on_the_data_volume():
    text = (REPO / "Dockerfile").read_text()
    assert "libusb-1.0-0" in text  # open3d does not import without it
    assert "pip install" in text and "DRONESIM_DATA_DIR=/data" in text
    assert 'CMD ["python", "-m", "server", "serve"]' in text
    # The page's npm modules are installed at the locked versions and copied in.
    assert (
        "npm ci" in text and "COPY --from=web /web/node_modules ./client_web/node_modules" in text
    )
    assert "client_web/node_modules" in (REPO / ".dockerignore").read_text()


def test_dockerfile_pins_its_bases_runs_unprivileged_checks_health_and_builds_extras():
    """Every base image an exact release (no bare `:20-slim`), dependencies from the lock, a
    non-root user that owns /data, a HEALTHCHECK on /healthz, and an EXTRAS build argument (the
    README's `--build-arg EXTRAS=ray`) that reaches the pip install."""
    text = (REPO / "Dockerfile").read_text()
    bases = re.findall(r"^FROM (\S+)", text, re.M)
    assert bases and all(re.search(r":\d+\.\d+\.\d+-", b) for b in bases), bases
    assert "-c /tmp/constraints.txt" in text and "COPY constraints.txt" in text
    users = re.findall(r"^USER (\S+)", text, re.M)
    assert users and users[-1] not in ("root", "0")
    assert text.index("USER ") > text.index("chown")
    assert re.search(r"^HEALTHCHECK .*\n?.*/healthz", text, re.M)
    assert "ARG EXTRAS" in text and "${EXTRAS:+[$EXTRAS]}" in text
    assert "--build-arg EXTRAS=ray" in _docs()
    pins = (REPO / "constraints.txt").read_text()
    assert re.search(r"^open3d-cpu==", pins, re.M) and re.search(r"^fastapi==", pins, re.M)


def test_health_endpoint_answers(live_server):
    import httpx

    server = live_server()
    body = httpx.get(f"{server.url}/healthz").json()
    assert body["status"] == "ok" and body["live_sessions"] == 0


def test_compose_phone_profile_serves_tls_on_its_own_port_and_volume_as_the_readme_says():
    """`docker compose --profile phone up`: TLS on (a phone's camera needs a secure origin),
    the certificate on a volume of its own (accepted once, kept), the same port inside and out
    (the printed URL names it), the host's LAN address passed in, an HTTPS health check."""
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    phone, server = compose["services"]["phone"], compose["services"]["server"]
    assert phone["profiles"] == ["phone"] and phone["image"] == server["image"]
    env = phone["environment"]
    assert set(env) <= {f"DRONESIM_{name.upper()}" for name in FLAT_ENV}
    assert env["DRONESIM_TLS"] == "true" and env["DRONESIM_HOST"] == "0.0.0.0"
    assert env["DRONESIM_PHONE_HOSTS"] == "${DRONESIM_PHONE_HOSTS:-}"  # from the shell, or none
    port = env["DRONESIM_PORT"]
    assert phone["ports"] == [f"{port}:{port}"] and f"{port}:" not in " ".join(server["ports"])
    volume, mount = phone["volumes"][0].split(":")
    assert mount == env["DRONESIM_DATA_DIR"] and volume in compose["volumes"]
    assert volume not in {v.split(":")[0] for v in server["volumes"]}  # two servers, two stores
    health = " ".join(phone["healthcheck"]["test"])
    assert f"https://127.0.0.1:{port}/healthz" in health and "unverified" in health
    assert "docker compose --profile phone up" in _docs()
