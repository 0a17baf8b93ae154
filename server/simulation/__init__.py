"""Drone simulation in the fused map: flight world model, route planning, quadrotor dynamics.

Everything here works in a gravity-aligned flight frame: metres, z up, gravity along -z.
"""
