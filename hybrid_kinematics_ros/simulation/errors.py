"""Errors of the virtual cell."""


class SimulationError(ValueError):
    """A virtual-cell setting that cannot be used; the message names the config field."""
