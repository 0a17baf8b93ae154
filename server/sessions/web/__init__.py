"""The web process's side of live sessions: modules that run in the server's one web process, beside
the event loop and Starlette's thread pool. A ``LiveSession`` is a session as the transport sees it
(frames in, updates out, a socket's takeover), the ``SessionManager`` creates, finds, closes and
saves sessions and chooses where each runs, and ``Viewers`` hands out viewer links and keeps their
map backlog. None of this tracks, maps or flies: that happens in the session's worker process
(``server.sessions.runtime``), reached through ``server.sessions.processes``.
"""
