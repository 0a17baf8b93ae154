"""AR drone simulator server: RGB-D registration, map fusion and a virtual drone.

Layout (one folder per stage; the numerical core imports nothing from the transport):
- ``geometry``      camera model and SE(3) helpers shared by every stage
- ``registration``  the paper's RGB-D odometry (FAST + LK + Gauss-Newton, dense refinement)
- ``mapping``       fusing registered frames into a map
- ``evaluation``    trajectory files and metrics (ATE, RPE)
- ``datasets``      one loader per RGB-D format behind one interface, plus the demo sequence
- ``simulation``    the drone: physics, collisions against the map, planned routes, courses
- ``rooms``         maps kept between sessions, and relocalising a new session into one
- ``sessions``      a live session's tracking, fusion and drone, and the processes they run in
- ``protocol``      the wire messages (``shared/protocol.json``)
- ``transport``     the FastAPI app: REST routes, WebSocket sessions, uploads
- ``client``        the load tester and replay clients
"""

from importlib.metadata import PackageNotFoundError, version

try:  # pyproject.toml is the one place the version is written
    __version__ = version("dronesim-ar")
except PackageNotFoundError:  # a checkout on sys.path without an install
    __version__ = "0+unknown"
