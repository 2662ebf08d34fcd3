"""Errors that the command line reports as one line."""


class InputError(Exception):
    """Bad user input (scene file, mesh file, option); the CLI prints it as one line and exits 2."""


class SimulationError(Exception):
    """A run that cannot go on (NaN or Inf in the state); the CLI prints it as one line and exits 1."""
