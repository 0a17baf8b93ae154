"""Drone simulation in the fused map: flight world model, route planning, quadrotor dynamics.

Everything here works in a gravity-aligned flight frame: metres, z up, gravity along -z.
"""

# The drone itself: configuration, dynamics, controller and the per-session simulator.
from server.simulation.config import SimulationConfig as SimulationConfig
from server.simulation.drone import DroneSimulator as DroneSimulator
from server.simulation.drone_types import DroneCommandError as DroneCommandError
from server.simulation.drone_types import DroneEvent as DroneEvent
from server.simulation.drone_types import DroneEventKind as DroneEventKind
from server.simulation.drone_types import DroneMode as DroneMode
from server.simulation.drone_types import DroneStatus as DroneStatus
