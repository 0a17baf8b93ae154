"""Helpers the tiers share (not tests, and no fixtures: those are in the conftest.py files):
the repository's paths, the browser and the emulated WebXR device of the browser tests, iPhone
recordings made from the shared data, the command line run as a user runs it, GLB files read
back."""
