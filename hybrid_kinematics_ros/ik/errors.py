"""Errors of inverse kinematics input (a failed solve is a result with ``success = False``, not an error)."""


class IKError(ValueError):
    """An IK request that cannot be posed: wrong seed length, non-finite target, bad options."""
