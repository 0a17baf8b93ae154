"""The wire protocol's definition, shared by the server and the phone page: ``protocol.json``
(machine-readable) and ``PROTOCOL.md`` (the spec). A package so that both ship as package data:
read the definition as ``importlib.resources.files("shared") / "protocol.json"``, which works in
a checkout and in an installed wheel alike."""
