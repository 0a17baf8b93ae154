"""The protocol's single definition, ``shared/protocol.json``, loaded as package data.

Everything else in ``server.protocol`` reads its limits, message fields, error codes and close
codes from here, so the server, the Python clients and the phone page agree by construction.
"""

from __future__ import annotations

import json
from importlib.resources import files

# The very file /protocol.json serves: a Path in a checkout or an installed wheel.
PROTOCOL_PATH = files("shared") / "protocol.json"
SPEC: dict = json.loads(PROTOCOL_PATH.read_text(encoding="utf-8"))
VERSION: int = SPEC["version"]
LIMITS: dict = SPEC["limits"]
MESSAGES: dict = SPEC["messages"]
ERRORS: dict[str, dict] = {e["name"]: e for e in SPEC["errors"]}
ERROR_NAMES: dict[int, str] = {e["code"]: e["name"] for e in SPEC["errors"]}
CLOSE_CODES: dict[str, int] = {c["name"]: c["code"] for c in SPEC["close_codes"]}
MAX_SEQ: int = next(f["max"] for f in MESSAGES["frame"]["fields"] if f["name"] == "seq")
CLIENT_TO_SERVER = "client_to_server"
SERVER_TO_CLIENT = "server_to_client"
