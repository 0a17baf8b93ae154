"""What runs inside a session's worker process (a process forked from the forkserver, or a Ray
actor): the host that answers the web process's calls, and the session it hosts, with its
tracking, mapping, loop and flight threads, the drone and its course, the room's keyframes and
the snapshots. Nothing here imports the web process's side (``server.sessions.web``); the map
and the loop closer it drives live in processes of their own, reached through clients in
``server.sessions.processes``.
"""
