"""Errors of the kinematics core."""


class KinematicsError(ValueError):
    """A URDF, robot config or joint input the kinematics core cannot use; the message says what to fix."""
