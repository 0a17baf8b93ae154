"""The wheel is the product: built from this checkout, installed into a fresh virtual environment
outside it and run from a folder outside it, it serves the page, every module file the page
imports and ``/protocol.json``, and ``track demo`` writes its results, through ``python -m
server`` and the ``dronesim`` console script alike.

The virtual environment sees the machine's site-packages for the dependencies (open3d & co.
would take minutes to install), and those may hold an editable install of this very project:
each test therefore proves that ``server``, ``shared`` and ``client_web`` are imported from the
virtual environment, never from the checkout.
"""

from __future__ import annotations

import ast
import email.parser
import json
import os
import re
import shutil
import signal
import site
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import zipfile
from dataclasses import dataclass
from html.parser import HTMLParser
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from urllib.parse import urljoin

import pytest

from tests.conftest import missing
from tests.support.paths import REPO

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

PACKAGES = ("server", "shared", "client_web")
# An ES module's static and dynamic imports: `import x from "m"`, `import {a,\n b} from "m"`,
# `import "m"`, `export * from "m"`, `import("m")`. The clause between the keyword and `from`
# holds no quote, so the pattern never reaches into a string.
IMPORT = re.compile(
    r"""\b(?:import|export)\s*(?:[\w*{}\s,$]*?\bfrom\s*)?["']([^"']+)["']"""
    r"""|\bimport\(\s*["']([^"']+)["']\s*\)"""
)


@dataclass
class Installed:
    """The wheel installed in a fresh virtual environment outside the checkout."""

    wheel: Path
    venv: Path
    python: Path
    site_packages: Path
    cwd: Path  # outside the checkout: the commands run from here
    env: dict[str, str]

    def run(self, *args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*args],
            cwd=self.cwd,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )


def _check_build_tools() -> None:
    """The wheel is built without build isolation (no download at test time): the environment's
    setuptools must be one that needs no separate ``wheel`` package (the dev extras' pin)."""
    try:
        major, minor = (int(part) for part in version("setuptools").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        missing("setuptools is not installed (dev extras: pip install -e '.[dev]')")
        return
    if (major, minor) < (77, 0):
        missing(f"setuptools {major}.{minor} < 77 (dev extras: pip install -e '.[dev]')")


def _copy_checkout(dst: Path) -> None:
    """The files git would commit (tracked, and untracked ones not ignored), so the build writes
    its build/ and egg-info there, not into the checkout; the page's npm modules (ignored) are
    linked in from the checkout."""
    try:
        listing = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=REPO,
            capture_output=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        missing(f"git cannot list the checkout's files: {exc}")
        return
    for name in filter(None, listing.decode().split("\0")):
        if name.startswith("client_web/node_modules"):
            continue
        source = REPO / name
        if source.is_file():  # a file deleted but not yet committed is listed too
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dst / name)
    modules = REPO / "client_web" / "node_modules"
    if not (modules / "three").is_dir():
        pytest.fail("client_web/node_modules is missing: `npm ci` in client_web (scripts/setup.sh)")
    (dst / "client_web" / "node_modules").symlink_to(modules.resolve(), target_is_directory=True)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    _check_build_tools()
    root = tmp_path_factory.mktemp("packaging")
    source, wheels, venv, cwd = (root / name for name in ("source", "wheels", "venv", "elsewhere"))
    for folder in (source, cwd):
        folder.mkdir()
    _copy_checkout(source)

    def call(*args) -> None:
        proc = subprocess.run(args, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, f"{' '.join(map(str, args))}:\n{proc.stdout}\n{proc.stderr}"

    call(sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         "--no-index", "-w", wheels, source)  # fmt: skip
    (wheel,) = wheels.glob("dronesim_ar-*.whl")
    call(sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", venv)
    python = venv / "bin" / "python"
    # The machine's pip, run by the venv's interpreter, installs into the venv; --ignore-installed
    # because the machine's site-packages may already hold this project (editable).
    call(python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--ignore-installed",
         wheel)  # fmt: skip
    purelib = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    # The dependencies the caller's environment holds beyond the machine's (a .venv made with
    # --system-site-packages, as scripts/setup.sh makes it, gets only what the machine lacks):
    # listed as plain paths, after the venv's own, so their .pth files (this project's editable
    # install among them) are not run.
    seen = subprocess.run(
        [python, "-c", "import sys; print('\\n'.join(sys.path))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    extra = [p for p in site.getsitepackages() if p not in seen]
    (Path(purelib) / "_caller_site_packages.pth").write_text("".join(f"{p}\n" for p in extra))
    # Nothing from the caller steers the imports or the server: no PYTHONPATH, no settings.
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV")
        and not (k.startswith("DRONESIM_") and k != "DRONESIM_CACHE")
    }
    return Installed(wheel, venv, python, Path(purelib), cwd, env)


def test_the_project_is_imported_from_the_wheel_not_the_checkout(installed):
    probe = (
        "import importlib, importlib.metadata, json, sys;"
        f"names = {PACKAGES!r};"
        "files = {n: importlib.import_module(n).__file__ for n in names};"
        "from importlib.resources import files as res;"
        "spec = res('shared') / 'protocol.json';"
        "dist = importlib.metadata.distribution('dronesim-ar');"
        "print(json.dumps({'files': files, 'spec': str(spec), 'spec_ok': spec.is_file(),"
        " 'dist': str(dist.locate_file(''))}))"
    )
    # `python -m server` resolves `server` exactly as this does: same interpreter, cwd, env.
    proc = installed.run(str(installed.python), "-c", probe)
    assert proc.returncode == 0, proc.stderr
    found = json.loads(proc.stdout)
    for name, file in found["files"].items():
        path = Path(file).resolve()
        assert path.is_relative_to(installed.site_packages.resolve()), (name, path)
        assert not path.is_relative_to(REPO), (name, path)
    assert found["spec_ok"] and Path(found["spec"]).is_relative_to(installed.site_packages)
    assert Path(found["dist"]).resolve() == installed.site_packages.resolve()
    # The console script runs the venv's interpreter.
    script = installed.venv / "bin" / "dronesim"
    assert script.read_text().splitlines()[0] == f"#!{installed.python}"


class _PageLinks(HTMLParser):
    """index.html's import map, module scripts and linked files (styles, icon)."""

    def __init__(self) -> None:
        super().__init__()
        self.import_map: dict[str, str] = {}
        self.scripts: list[str] = []
        self.links: list[str] = []
        self._in_import_map = False

    def handle_starttag(self, tag, attrs) -> None:
        a = dict(attrs)
        if tag == "script" and a.get("type") == "importmap":
            self._in_import_map = True
        elif tag == "script" and a.get("src"):
            self.scripts.append(a["src"])
        elif tag == "link" and a.get("href"):
            self.links.append(a["href"])

    def handle_data(self, data) -> None:
        if self._in_import_map:
            self.import_map.update(json.loads(data)["imports"])
            self._in_import_map = False


def _resolve(specifier: str, base: str, import_map: dict[str, str]) -> str:
    """A module specifier as the browser resolves it: relative to the importing module's URL,
    or through the import map (exact names, then the longest matching prefix ending in /)."""
    if specifier.startswith(("/", "./", "../")):
        return urljoin(base, specifier)
    if specifier in import_map:
        return import_map[specifier]
    prefixes = [p for p in import_map if p.endswith("/") and specifier.startswith(p)]
    if not prefixes:
        raise AssertionError(f"{base} imports {specifier!r}, which the import map does not name")
    prefix = max(prefixes, key=len)
    return import_map[prefix] + specifier[len(prefix) :]


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_wheel_says_its_licence_version_and_dependencies(installed):
    """The wheel's metadata: an SPDX licence with the licence texts (ours and the vendored
    modules' notices), the README as its description, one version (pyproject's, which the
    installed server and its OpenAPI report), and every package the server imports declared."""
    with zipfile.ZipFile(installed.wheel) as wheel:
        info = next(n.rsplit("/", 1)[0] for n in wheel.namelist() if n.endswith("/METADATA"))
        metadata = email.parser.Parser().parsestr(wheel.read(f"{info}/METADATA").decode())
        names = set(wheel.namelist())
    assert metadata["License-Expression"] == "MIT"
    assert {f"{info}/licenses/LICENSE", f"{info}/licenses/THIRD_PARTY_NOTICES.md"} <= names
    assert metadata["Description-Content-Type"] == "text/markdown"
    assert metadata.get_payload().startswith("# AR drone simulator")
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert metadata["Version"] == pyproject["version"]
    probe = (
        "import json, server; from server.transport.app import create_app;"
        "from server.config import Config;"
        "print(json.dumps([server.__version__, create_app(Config()).version]))"
    )
    proc = installed.run(str(installed.python), "-c", probe)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.splitlines()[-1]) == [pyproject["version"]] * 2
    # Every third-party top-level package imported anywhere in server/ is a declared dependency.
    declared = {
        re.split(r"[\[<>=; ]", d)[0].lower().replace("-", "_")
        for d in metadata.get_all("Requires-Dist")
        if "extra ==" not in d or 'extra == "ray"' in d
    }
    imported_as = {"cv2": "opencv_python_headless", "yaml": "pyyaml", "open3d": "open3d_cpu"}
    imported = set()
    for path in (REPO / "server").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split(".")[0])
    third_party = imported - set(sys.stdlib_module_names) - {"server", "shared", "client_web"}
    undeclared = {m for m in third_party if imported_as.get(m, m) not in declared}
    assert not undeclared, f"imported by server/ but not declared in pyproject.toml: {undeclared}"


def test_serve_from_the_wheel_serves_the_page_its_modules_and_the_protocol(installed, tmp_path):
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    log = tmp_path / "serve.log"
    with log.open("wb") as out:
        server = subprocess.Popen(
            [str(installed.python), "-m", "server", "serve", "--host", "127.0.0.1",
             "--port", str(port), "--data-dir", str(tmp_path / "data"), "--no-demo"],
            cwd=installed.cwd,
            env=installed.env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
    try:
        deadline = time.monotonic() + 90
        while _get_health(base) != 200:
            assert server.poll() is None, f"serve exited:\n{log.read_text()[-3000:]}"
            assert time.monotonic() < deadline, f"serve did not start:\n{log.read_text()[-3000:]}"
            time.sleep(0.2)

        status, index = _get(f"{base}/")
        assert status == 200 and b"<script" in index
        page = _PageLinks()
        page.feed(index.decode())
        assert page.import_map and page.scripts, "index.html lost its import map or its script"
        for href in page.links:  # styles, icon
            assert _get(urljoin(f"{base}/", href))[0] == 200, href

        # Every module the page loads, followed through its imports, as the browser would.
        served: dict[str, bytes] = {}
        todo = list(page.scripts)
        while todo:
            url = todo.pop()
            if url in served:
                continue
            status, body = _get(f"{base}{url}")
            assert status == 200, f"{url}: {status} {body[:200]!r}"
            served[url] = body
            for match in IMPORT.finditer(body.decode()):
                todo.append(_resolve(match.group(1) or match.group(2), url, page.import_map))
        assert "/app/js/network/protocol.js" in served  # one of the page's own modules
        assert "/vendor/three/build/three.module.js" in served
        assert "/vendor/@msgpack/msgpack/dist.esm/index.mjs" in served
        assert "/vendor/uqr/dist/index.mjs" in served  # the invitation's QR code

        status, spec = _get(f"{base}/protocol.json")
        assert status == 200 and spec == (REPO / "shared" / "protocol.json").read_bytes()
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(60)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(30)

    # The wheel holds the vendored files the page loads (and their licences), nothing more.
    with zipfile.ZipFile(installed.wheel) as wheel:
        vendored = {n for n in wheel.namelist() if n.startswith("client_web/node_modules/")}
        spec_in_wheel = wheel.read("shared/protocol.json")
    loaded = {
        "client_web/node_modules/" + url.removeprefix("/vendor/")
        for url in served
        if url.startswith("/vendor/")
    }
    licences = {n for n in vendored if n.endswith("/LICENSE")}
    assert vendored - licences == loaded
    assert {p.split("/")[2].lstrip("@") for p in licences} == {"three", "msgpack", "uqr"}
    assert spec_in_wheel == spec


def _get_health(base: str) -> int | None:
    try:
        return _get(f"{base}/healthz")[0]
    except OSError:  # not listening yet
        return None


def test_dronesim_track_demo_from_the_wheel_writes_its_results(installed, tmp_path):
    out = tmp_path / "track"
    frames = 12
    proc = installed.run(
        str(installed.venv / "bin" / "dronesim"),
        "track",
        "demo",
        "--out",
        str(out),
        "--frames",
        str(frames),
        timeout_s=300,
    )
    assert proc.returncode == 0, f"{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    out = out / "latest"  # each run's own folder under --out
    rows = [
        [float(v) for v in line.split()]
        for line in (out / "trajectory.tum").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert len(rows) == frames and all(len(r) == 8 for r in rows)
    assert all(abs(sum(q * q for q in r[4:]) - 1.0) < 1e-6 for r in rows)  # unit quaternions
    header = (out / "map.ply").read_bytes()[:400]
    assert header.startswith(b"ply\n")
    points = int(re.search(rb"element vertex (\d+)", header).group(1))
    assert points > 1000, points
    assert (out / "trajectory.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == frames and sum(summary["states"].values()) == frames
    assert summary["metrics"] is not None  # the demo carries its ground truth
