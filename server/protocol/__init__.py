"""The wire protocol, defined once in ``shared/protocol.json`` (see ``shared/PROTOCOL.md``).

``encode``/``decode`` check every message against that definition and raise ``ProtocolError``
with one of its error code names. The ``make_*`` helpers build messages from numpy data
(images are JPEG / PNG / zlib encoded, map points packed little-endian); ``decode_frame_images``
turns a frame back into an RGB image and a depth map in metres; ``ClientOrder`` holds the order
rules of a client's messages. Modules: ``spec`` (the definition), ``errors``, ``schema``
(validation), ``messages`` (builders, msgpack), ``peek`` (a message's type and seq, read without
decoding it), ``codecs`` (images), ``order``.

Used by the server (``server.transport``, ``server.sessions``) and the Python clients
(``server.client``) alike; it imports neither.
"""

from server.protocol.codecs import decode_frame_images, encode_depth, encode_jpeg
from server.protocol.errors import ProtocolError, make_error
from server.protocol.messages import (
    decode,
    decode_map_chunk,
    decode_map_corrected,
    depth_intrinsics,
    encode,
    make_bye,
    make_command,
    make_course,
    make_drone_event,
    make_drone_state,
    make_frame,
    make_hello,
    make_map_chunk,
    make_map_corrected,
    make_pose,
    make_room,
    make_welcome,
    pose_matrix,
    queued_frames,
)
from server.protocol.order import ClientOrder
from server.protocol.peek import Peek, peek
from server.protocol.schema import validate
from server.protocol.spec import (
    CLIENT_TO_SERVER,
    CLOSE_CODES,
    ERROR_NAMES,
    ERRORS,
    LIMITS,
    MESSAGES,
    PROTOCOL_PATH,
    SERVER_TO_CLIENT,
    SPEC,
    VERSION,
)

__all__ = [
    "CLIENT_TO_SERVER",
    "CLOSE_CODES",
    "ERRORS",
    "ERROR_NAMES",
    "LIMITS",
    "MESSAGES",
    "PROTOCOL_PATH",
    "SERVER_TO_CLIENT",
    "SPEC",
    "VERSION",
    "ClientOrder",
    "Peek",
    "ProtocolError",
    "decode",
    "decode_frame_images",
    "decode_map_chunk",
    "decode_map_corrected",
    "depth_intrinsics",
    "encode",
    "encode_depth",
    "encode_jpeg",
    "make_bye",
    "make_command",
    "make_course",
    "make_drone_event",
    "make_drone_state",
    "make_error",
    "make_frame",
    "make_hello",
    "make_map_chunk",
    "make_map_corrected",
    "make_pose",
    "make_room",
    "make_welcome",
    "peek",
    "pose_matrix",
    "queued_frames",
    "validate",
]
