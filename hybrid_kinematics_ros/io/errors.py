"""Errors of bag, CSV and model-directory input and output."""


class DataError(ValueError):
    """Input data that cannot be used; the message names the file and what is wrong with it."""
