"""Errors of the served model: loading its calibration sections and answering requests."""


class ModelError(ValueError):
    """The model cannot answer as asked: a malformed ``model.json`` section, a configuration outside the
    calibrated range under the ``refuse`` policy, an unknown condition channel or range policy; the message
    says which."""
