"""The module map of docs/ARCHITECTURE.md, held to the code: which server packages may import
which, read from the sources with ``ast`` (nothing is imported), and the document's paths and
close codes checked against the tree and the protocol, so that neither can silently rot."""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path

import pytest

from tests.support.paths import REPO

SERVER = REPO / "server"
DOC = REPO / "docs" / "ARCHITECTURE.md"

_WEB = ("fastapi", "starlette", "uvicorn", "websockets")
# The numerical core works on arrays: no web, wire format, settings machinery, sessions or files.
_CORE_FORBIDS = (
    "server.transport",
    "server.sessions",
    "server.client",
    "server.protocol",
    "server.config",
    "server.cli",
    "server.pipeline",
    "server.datasets",
    *_WEB,
    "msgpack",
    "pydantic",
    "pydantic_settings",
    "ray",
    "typer",
)

# package (a folder under server/, or a module) -> the imports it must never make (prefixes).
RULES: dict[str, tuple[str, ...]] = {
    "geometry": _CORE_FORBIDS,
    "registration": _CORE_FORBIDS,
    "simulation": _CORE_FORBIDS,
    "mapping": _CORE_FORBIDS,
    # rooms joins registration and mapping on files; sessions and the CLI use it.
    "rooms": _CORE_FORBIDS,
    # evaluation owns trajectories: datasets use it, never the other way round.
    "evaluation": _CORE_FORBIDS,
    "datasets": tuple(p for p in _CORE_FORBIDS if p != "server.datasets"),
    # The wire format alone: no sessions, no numerical stage, no web framework.
    "protocol": (
        "server.transport",
        "server.sessions",
        "server.client",
        "server.config",
        "server.registration",
        "server.mapping",
        "server.simulation",
        "server.datasets",
        "server.evaluation",
        *_WEB,
        "pydantic",
        "ray",
    ),
    # Live sessions know no web code: the transport hands them bytes and takes updates back.
    "sessions": ("server.transport", "server.client", "server.cli", *_WEB, "typer"),
    # What runs in a session's worker process never reaches for the web process's side of it.
    "sessions/runtime": ("server.sessions.web", "server.transport", *_WEB),
    # A client speaks the protocol over the network, never through the server's insides.
    "client": ("server.transport", "server.sessions", "server.cli", "fastapi", "starlette"),
    # The configuration gathers the sections; it knows no layer that reads it.
    "config": (
        "server.transport",
        "server.sessions",
        "server.client",
        "server.protocol",
        "server.cli",
    ),
}


def imported_modules(source: str, module: str) -> set[str]:
    """Every module ``source`` (the text of ``module``, dotted) imports, at any depth (a lazy
    import inside a function counts too). ``from server import protocol`` gives
    ``server.protocol``; relative imports are resolved against ``module``."""
    found: set[str] = set()
    package = module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def _is_under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _files(package: str) -> list[Path]:
    folder = SERVER / package
    return sorted(folder.rglob("*.py")) if folder.is_dir() else [SERVER / f"{package}.py"]


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def violations(package: str, forbidden: tuple[str, ...]) -> list[str]:
    found = []
    for path in _files(package):
        module = _module_name(path)
        names = imported_modules(path.read_text(), module)
        for prefix in forbidden:
            hits = [n for n in names if _is_under(n, prefix)]
            if hits:  # the module itself, not each name taken from it
                name = min(hits, key=len)
                found.append(f"{path.relative_to(REPO)} imports {name} (forbidden: {prefix})")
    return found


@pytest.mark.parametrize("package", sorted(RULES))
def test_package_imports_nothing_it_must_not(package):
    files = _files(package)
    assert files and all(f.is_file() for f in files), f"server/{package} is gone: update RULES"
    assert violations(package, RULES[package]) == []


def test_the_import_reader_sees_every_form_of_import():
    source = (
        "import fastapi.routing\n"
        "from server import protocol as proto\n"
        "from server.sessions.live import LiveSession\n"
        "def later():\n"
        "    from ..transport import app\n"
    )
    found = imported_modules(source, "server.client.replay")
    assert {"fastapi.routing", "server.protocol", "server.sessions.live"} <= found
    assert "server.transport.app" in found  # relative, inside a function
    assert any(_is_under(n, "server.transport") for n in found)
    assert not _is_under("server.transports", "server.transport")


def test_a_violation_is_reported(tmp_path, monkeypatch):
    """The check is not vacuous: a core module that imports the transport is caught."""
    package = tmp_path / "server" / "geometry"
    package.mkdir(parents=True)
    (package / "bad.py").write_text("from server.transport.websocket import router\n")
    this = sys.modules[__name__]
    monkeypatch.setattr(this, "SERVER", tmp_path / "server")
    monkeypatch.setattr(this, "REPO", tmp_path)
    assert violations("geometry", RULES["geometry"]) == [
        "server/geometry/bad.py imports server.transport.websocket (forbidden: server.transport)"
    ]


def import_graph(root: Path) -> dict[str, set[str]]:
    """server module -> the server modules it imports (lazy and type-checking imports count:
    each is a dependency a reader follows). A name taken from a package is its __init__'s."""
    paths = {_module_name(p): p for p in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        targets = set()
        for name in imported_modules(path.read_text(), module):
            while name and name not in paths:  # a name from a module: the module
                name = name.rpartition(".")[0]
            if name and name != module:
                targets.add(name)
        graph[module] = targets
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.append(member)
                    if member == node:
                        break
                if len(group) > 1:
                    circles.append(sorted(group))
    return circles


def test_no_module_of_the_server_imports_itself_in_a_circle():
    """No import circles in server/: each module can be read (and tested) after the ones it
    imports, lazy imports inside functions and type-checking imports included."""
    assert import_circles(import_graph(SERVER)) == []


def test_an_import_circle_is_found(tmp_path, monkeypatch):
    """The check is not vacuous: a circle through a lazy import is caught, and a chain is not."""
    package = tmp_path / "server" / "sessions"
    package.mkdir(parents=True)
    (package / "a.py").write_text("from server.sessions.b import B\n")
    (package / "b.py").write_text("def f():\n    from server.sessions.c import C\n")
    (package / "c.py").write_text("from server.sessions import a\n")
    (package / "d.py").write_text("from server.sessions.a import A\n")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    graph = import_graph(tmp_path / "server")
    assert import_circles(graph) == [
        ["server.sessions.a", "server.sessions.b", "server.sessions.c"]
    ]


def test_ray_stays_optional():
    """Ray is imported by server/sessions/processes/ray_workers.py alone, and that module only
    from inside a function (``serve --ray``): without it, Ray is never imported."""
    ray_module = SERVER / "sessions" / "processes" / "ray_workers.py"
    for path in sorted(SERVER.rglob("*.py")):
        tree = ast.parse(path.read_text())
        module = _module_name(path)
        if path != ray_module:
            assert not any(_is_under(n, "ray") for n in imported_modules(path.read_text(), module))
        top_level = ast.Module(
            body=[n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)],
            type_ignores=[],
        )
        at_start = imported_modules(ast.unparse(top_level), module)
        ray_at_start = "server.sessions.processes.ray_workers" in at_start
        assert not ray_at_start, f"{path} imports Ray at start"


# ---- the document against the tree ------------------------------------------------------------


def test_the_architecture_document_names_only_what_exists():
    text = DOC.read_text()
    paths = set(re.findall(r"\b((?:server|shared|tests|client_web|benchmarks)/[\w./-]*\w)", text))
    assert paths, "no paths found: has the document's style changed?"
    # Paths written relative to server/ (``sessions/store.py``) are checked there.
    packages = "|".join(p.name for p in SERVER.iterdir() if (p / "__init__.py").is_file())
    relative = re.findall(rf"(?<![\w/])((?:{packages})/(?:\w+/)*[\w.]+\.py)\b", text)
    assert relative, "no server-relative paths found: has the document's style changed?"
    paths |= {f"server/{p}" for p in relative}
    missing = sorted(p for p in paths if not (REPO / p).exists())
    assert missing == [], f"docs/ARCHITECTURE.md names paths that do not exist: {missing}"


def test_the_module_map_covers_every_package():
    text = DOC.read_text()
    module_map = text.split("## Module map", 1)[1]
    packages = [p.name for p in SERVER.iterdir() if p.is_dir() and (p / "__init__.py").exists()]
    assert packages
    absent = [p for p in packages if f"`{p}/`" not in module_map]
    assert absent == [], f"packages missing from the module map: {absent}"
    for package in RULES:  # every rule this test holds is stated there too
        shown = f"`{package}/`" if (SERVER / package).is_dir() else f"`{package}.py`"
        assert shown in module_map


def test_the_close_codes_match_the_protocol():
    spec = json.loads((REPO / "shared" / "protocol.json").read_text())
    codes = {c["name"]: c["code"] for c in spec["close_codes"]}
    quoted = re.findall(r"`(\w+)`,?\s(?:close\s)?(4\d{3})\b", DOC.read_text())
    assert len(quoted) >= 8, "the failure table quotes its close codes as `name` 4010"
    wrong = [(name, int(code)) for name, code in quoted if codes.get(name) != int(code)]
    assert wrong == []
