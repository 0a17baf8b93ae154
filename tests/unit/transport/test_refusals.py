"""A session's refusals as the client hears them: one mapping for both roads a refusal takes
from the session's worker (a call's SessionError, a frame's FrameRefused update)."""

from __future__ import annotations

from server.transport.websocket import _SESSION_CODES, _refusal


def test_every_session_code_is_a_protocol_error():
    for code, name in _SESSION_CODES.items():
        assert _refusal(code, "refused", 3).code == name


def test_a_protocol_error_s_name_stays_with_its_seq_and_whether_it_counts():
    error = _refusal("bad_depth", "no depth", 5, counted=False)
    assert (error.code, error.seq, error.counted, error.fatal) == ("bad_depth", 5, False, False)
    error = _refusal("invalid_field", "frame.timestamp must be float", 9)
    assert error.fatal and error.to_message()["seq"] == 9
    assert _refusal("bad_sequence", "seq 3 after seq 5", 3).to_message()["seq"] == 3


def test_a_code_the_protocol_does_not_name_is_an_internal_error():
    error = _refusal("server_full", "no room", None)
    assert error.code == "internal_error" and not error.fatal
