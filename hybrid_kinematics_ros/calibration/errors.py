"""Errors of calibration: training, model directories and evaluation."""


class CalibrationError(ValueError):
    """Training or a model directory cannot proceed; the message says which file, field or value to fix."""
