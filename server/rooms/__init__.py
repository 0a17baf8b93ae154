"""Rooms: the keyframes, place features and map a session leaves, to continue in later."""

from server.rooms.room import Room, RoomError, RoomKeyframe, load_room, save_room

__all__ = ["Room", "RoomError", "RoomKeyframe", "load_room", "save_room"]
