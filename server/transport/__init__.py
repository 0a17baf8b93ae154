"""The web side of the server: FastAPI app, REST routes, the WebSocket endpoint and TLS.

The wire protocol itself is ``server.protocol``; pure numerical code (registration, mapping,
simulation) never imports from here, nor do the Python clients (``server.client``).
"""
