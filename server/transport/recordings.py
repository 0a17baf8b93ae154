"""Uploaded iPhone recordings, converted for the page's replay and kept under
``<data_dir>/recordings/<id>/``.

An upload (a Record3D ``.r3d`` or a zipped Stray Scanner export) is received into
``.incoming/`` with its size checked as it arrives, converted (``server.datasets.archives`` and
``replay_export``) into ``.staging-<id>/``, and renamed to ``<id>/`` only when whole; any
failure removes what it wrote, so an error leaves nothing behind. Conversion runs in a process
of its own (the sessions' forkserver) under a memory ceiling and a time limit: a small file
that inflates to gigabytes, or claims a million frames, costs that process, never the web
process, and is answered 422 like any other recording that cannot be read. Each recording is
read with the token its upload was answered with, as a session is: the store keeps only the
token's SHA-256, and an unknown id and a wrong token get the same answer.
"""

from __future__ import annotations

import hmac
import json
import logging
import resource
import secrets
import shutil
from collections.abc import AsyncIterator
from multiprocessing.connection import Connection
from pathlib import Path

from server.datasets.archives import UnknownRecording, open_recording_archive
from server.datasets.bounds import DecodeLimits
from server.datasets.replay_export import export_replay
from server.errors import DatasetError, DroneSimError
from server.sessions.processes.session_process import process_context
from server.sessions.store import hash_token

log = logging.getLogger(__name__)

# An unpacked Stray export may be this many times larger than its zip (depth PNGs barely
# compress further; a zip bomb would be far beyond it).
MAX_UNPACK_FACTOR = 4
_ID_CHARS = set("0123456789abcdef")
_NO_RECORDING_HASH = hash_token(secrets.token_urlsafe(32))  # compared against for unknown ids


class RecordingError(DroneSimError):
    """An upload or a request for a recording that cannot be honoured: ``code`` names the reason
    for the client, ``status`` is the HTTP status it is answered with."""

    def __init__(self, code: str, message: str, status: int) -> None:
        super().__init__(message)
        self.code, self.status = code, status


def recording_name(filename: str | None) -> str:
    """A name to show for an upload: its file name without folders and suffix, printable
    characters only, at most 64 ('recording' when nothing is left)."""
    stem = (filename or "").replace("\\", "/").rsplit("/", 1)[-1].rsplit(".", 1)[0]
    cleaned = "".join(c for c in stem if c.isprintable())[:64].strip()
    return cleaned or "recording"


class RecordingStore:
    """The recordings under ``root``; uploads of at most ``max_upload_bytes``, each converted
    in a process that may take ``memory_bytes`` more address space than it starts with and run
    ``convert_s`` seconds, and read within ``limits`` (what any member, image and frame list
    may declare)."""

    def __init__(
        self,
        root: Path,
        max_upload_bytes: int,
        memory_bytes: int,
        convert_s: float,
        limits: DecodeLimits,
    ) -> None:
        self.root = root
        self.max_upload_bytes = max_upload_bytes
        self.memory_bytes = memory_bytes
        self.convert_s = convert_s
        self.limits = limits

    def clean(self) -> None:
        """Remove what an interrupted upload or conversion left (at start-up)."""
        if not self.root.is_dir():
            return
        for leftover in [self.root / ".incoming", *self.root.glob(".staging-*")]:
            shutil.rmtree(leftover, ignore_errors=True)

    def too_large(self, size: int) -> RecordingError:
        return RecordingError(
            "upload_too_large",
            f"the upload is {size / 1e6:.1f} MB or more; this server takes at most "
            f"{self.max_upload_bytes / 1e6:.1f} MB (server.max_upload_mb)",
            413,
        )

    async def receive(self, body: AsyncIterator[bytes]) -> Path:
        """Write an upload's bytes to a file of its own under ``.incoming/``; refuse it (and
        remove the part written) once it passes ``max_upload_bytes``."""
        incoming = self.root / ".incoming"
        incoming.mkdir(parents=True, exist_ok=True)
        path = incoming / f"{secrets.token_hex(8)}.upload"
        size = 0
        try:
            with path.open("wb") as f:
                async for chunk in body:
                    size += len(chunk)
                    if size > self.max_upload_bytes:
                        raise self.too_large(size)
                    f.write(chunk)
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        if size == 0:
            path.unlink(missing_ok=True)
            raise RecordingError(
                "unsupported_recording", "the upload is empty: send the file as the body", 415
            )
        return path

    def convert(self, upload: Path, name: str) -> tuple[str, str, dict]:
        """Convert the upload at ``upload`` (removed in any case) into a recording called
        ``name`` -> (id, token, index with file names). RecordingError 415 for a file that is
        no recording, 422 for one that cannot be read."""
        recording_id = secrets.token_hex(8)
        token = secrets.token_urlsafe(32)
        staging = self.root / f".staging-{recording_id}"
        unpacked = self.root / ".incoming" / f"{recording_id}.unpacked"
        try:
            max_unpacked = MAX_UNPACK_FACTOR * self.max_upload_bytes
            index = self._export_apart(upload, unpacked, staging, max_unpacked)
            index |= {"name": name}
            (staging / "index.json").write_text(json.dumps(index))
            meta = {"id": recording_id, "token_sha256": hash_token(token), "name": index["name"]}
            (staging / "meta.json").write_text(json.dumps(meta))
            staging.rename(self.root / recording_id)  # whole, or not there at all
        except UnknownRecording as exc:
            message = _plain(exc, upload, unpacked, self.root)
            raise RecordingError("unsupported_recording", message, 415) from exc
        except DatasetError as exc:
            message = f"cannot read the recording: {_plain(exc, upload, unpacked, self.root)}"
            raise RecordingError("bad_recording", message, 422) from exc
        finally:
            upload.unlink(missing_ok=True)
            shutil.rmtree(unpacked, ignore_errors=True)
            shutil.rmtree(staging, ignore_errors=True)
        log.info("recording %s: %s, %d frames", recording_id, index["name"], len(index["frames"]))
        return recording_id, token, index

    def _export_apart(self, upload: Path, unpacked: Path, staging: Path, max_unpacked: int) -> dict:
        """``_export`` in a process of its own under the memory ceiling and time limit. Its
        failures come back as they would in the caller; running out of memory or time, or
        dying, is a DatasetError naming the limit."""
        ctx = process_context()
        receive, send = ctx.Pipe(duplex=False)
        process = ctx.Process(
            target=_export_in_child,
            args=(upload, unpacked, staging, max_unpacked, self.limits, self.memory_bytes, send),
            name="convert-upload",
            daemon=True,
        )
        process.start()
        send.close()
        try:
            if not receive.poll(self.convert_s):
                raise DatasetError(
                    f"converting it took longer than {self.convert_s:.0f} s "
                    "(server.upload_convert_s)"
                )
            try:
                outcome, value = receive.recv()
            except EOFError:
                outcome, value = "died", ""
        finally:
            receive.close()
            if process.is_alive():
                process.kill()
            process.join(10)
        if outcome == "ok":
            index: dict = value
            return index
        if outcome == "unknown":
            raise UnknownRecording(value)
        if outcome == "memory" or outcome == "died":
            # "died": under RLIMIT_AS a failed allocation in native code may abort the process
            # instead of raising MemoryError.
            raise DatasetError(
                f"converting it needs more than {self.memory_bytes / 2**20:.0f} MB of memory "
                "(server.upload_memory_mb): a recording that inflates this far is refused"
            )
        raise DatasetError(value)

    def folder(self, recording_id: str, token: str | None) -> Path:
        """The folder of the recording ``token`` opens. No token: 401; an unknown id or a wrong
        token: the same 404 after the same work."""
        if token is None:
            raise RecordingError(
                "unauthorized", "send the upload's token: Authorization: Bearer <token>", 401
            )
        expected, folder = _NO_RECORDING_HASH, None
        if len(recording_id) == 16 and set(recording_id) <= _ID_CHARS:
            candidate = self.root / recording_id
            try:
                meta = json.loads((candidate / "meta.json").read_text())
                expected, folder = str(meta["token_sha256"]), candidate
            except (OSError, ValueError, KeyError):
                pass
        if hmac.compare_digest(hash_token(token), expected) and folder is not None:
            return folder
        raise RecordingError("not_found", "no recording with this id for this token", 404)

    def index(self, folder: Path) -> dict:
        index: dict = json.loads((folder / "index.json").read_text())
        return index

    def delete(self, folder: Path) -> None:
        shutil.rmtree(folder)


def _plain(exc: BaseException, upload: Path, unpacked: Path, root: Path) -> str:
    """An error's message without the server's own paths (a client has no use for them): the
    upload's file ("<path>: " prefixes dropped), its unpacked folder (its files keep their names
    within it) and the recordings folder."""
    message = str(exc)
    for path in (upload, unpacked, root):
        for form in (str(path.resolve()), str(path)):
            message = message.replace(f"{form}: ", "").replace(f"{form}/", "")
            message = message.replace(form, "the upload" if path == upload else "")
    return message


def _export(
    upload: Path, unpacked: Path, staging: Path, max_unpacked: int, limits: DecodeLimits
) -> dict:
    """Read the upload (unpacking a Stray zip into ``unpacked``) within ``limits`` and write its
    replay into ``staging`` -> the replay's index."""
    dataset = open_recording_archive(upload, unpacked, max_unpacked, limits)
    return export_replay(dataset, staging)


def _export_in_child(
    upload: Path,
    unpacked: Path,
    staging: Path,
    max_unpacked: int,
    limits: DecodeLimits,
    memory_bytes: int,
    send: Connection,
) -> None:
    """The conversion process: ``_export`` with at most ``memory_bytes`` more address space
    than the process holds now; its outcome goes back over ``send`` as (kind, value). Any
    failure of reading is the recording's fault here: a bad file must never be a 500."""
    _limit_address_space(memory_bytes)
    try:
        index = _export(upload, unpacked, staging, max_unpacked, limits)
        outcome: tuple[str, object] = ("ok", index)
    except UnknownRecording as exc:
        outcome = ("unknown", str(exc))
    except MemoryError:
        outcome = ("memory", "")
    except DatasetError as exc:
        outcome = ("bad", str(exc))
    except Exception as exc:  # a reader that trips over a malformed file
        outcome = ("bad", f"{type(exc).__name__}: {exc}")
    send.send(outcome)
    send.close()


def _limit_address_space(extra_bytes: int) -> None:
    """RLIMIT_AS at the process's present address space plus ``extra_bytes``: what the forked
    process already maps (the numerical stack, imported once in the forkserver) stays usable."""
    size_kb = 0
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmSize:"):
                size_kb = int(line.split()[1])
    limit = size_kb * 1024 + extra_bytes
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
