"""One error base class for the project; subclasses where a caller needs to tell errors apart."""


class DroneSimError(Exception):
    """Base class of every error the project raises on purpose."""


class DatasetError(DroneSimError):
    """A dataset folder or file is missing, malformed or inconsistent."""


class TrajectoryError(DroneSimError):
    """A trajectory file is malformed, or two trajectories cannot be compared."""


class ConfigError(DroneSimError):
    """A configuration value is out of range or inconsistent."""
