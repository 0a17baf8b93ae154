"""How many native threads each live session's tracking gets."""

from server.sessions.config import threads_per_session


def test_sessions_share_every_core_but_one_which_their_other_work_keeps():
    assert threads_per_session(2, 1) == 1  # the other core: the mapper and the web process
    assert threads_per_session(16, 1) == 15
    assert threads_per_session(16, 4) == 3
    assert threads_per_session(16, 40) == 1  # never below one
    assert threads_per_session(1, 0) == 1
