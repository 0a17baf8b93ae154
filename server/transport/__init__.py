"""The WebSocket side of the server: the wire protocol codec (``protocol``), defined in ``shared/``.

Pure numerical code (registration, mapping, simulation) never imports from here.
"""
