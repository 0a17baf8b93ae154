"""Process plumbing: how a session's processes start and talk. The worker process and the
forkserver it comes from (``session_process``), the mapper process and its client (``mapper``),
the loop process and its client (``loop_process``), Ray actors in place of worker processes
(``ray_workers``, the actor's work in ``actor_host``, its processes started in a fresh
interpreter by ``fresh``), how they talk (``ipc``: requests,
replies, errors carried across a pipe as values, the serve loop and the callers' proxy) and the
thread priorities (``priority``). A handle here runs on the side that
owns the process (the web process for a worker, the worker for its mapper and loop process); a
``*_main`` function is the entry point of the process it starts.
"""
