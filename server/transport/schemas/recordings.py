"""Uploaded recordings: ``POST /api/recordings`` and the replay index it makes."""

from __future__ import annotations

from pydantic import Field

from server.transport.schemas.common import WireModel


class RecordingCreated(WireModel):
    """``POST /api/recordings`` answers 201 with this body once the upload is converted."""

    id: str = Field(
        description="the recording's id: 16 lowercase hex digits", pattern="^[0-9a-f]{16}$"
    )
    token: str = Field(
        description="the recording's secret, shown only in this answer: reading the index and "
        "its files needs `Authorization: Bearer <token>`. The server keeps only its SHA-256",
    )
    index: str = Field(description="URL of the replay's index (`GET`, with the token)")
    name: str = Field(description="the recording's name (the .r3d file's or the export's folder)")
    frames: int = Field(description="frames converted")


class RecordingFrame(WireModel):
    """One frame of a recording's replay index."""

    timestamp: float = Field(description="capture time, seconds (the phone's clock)")
    colour: str = Field(description="URL of the colour JPEG (needs the token)")
    depth: str = Field(description="URL of the 16-bit depth PNG, units of depth_scale")
    T_device_camera: list[float] | None = Field(
        None,
        min_length=16,
        max_length=16,
        description="the phone's own camera pose (ARKit odometry) in its world, 4x4 "
        "camera-to-world, row-major, metres, this protocol's camera axes (x right, y down, "
        "z forward): sent as frame.T_device_camera",
    )


class RecordingIndex(WireModel):
    """``GET /api/recordings/{id}``: what the page's replay needs, as ``/api/demo`` gives."""

    id: str = Field(description="the recording's id")
    name: str = Field(description="the recording's name")
    intrinsics: list[float] = Field(
        min_length=4, max_length=4, description="[fx, fy, cx, cy] of the colour image, px"
    )
    colour_size: list[int] = Field(min_length=2, max_length=2, description="[width, height], px")
    depth_size: list[int] = Field(min_length=2, max_length=2, description="[width, height], px")
    depth_scale: float = Field(description="depth PNG units per metre (1000: millimetres)")
    depth_format: str = Field(description="png")
    fps: float = Field(description="frames per second as recorded")
    gravity: list[float] | None = Field(
        None,
        description="gravity in the first camera's frame (unit vector), from ARKit's y-up world",
    )
    frames: list[RecordingFrame] = Field(description="the frames in order")
