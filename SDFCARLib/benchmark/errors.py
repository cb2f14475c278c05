"""The benchmark's error type (its own module, so that every other module can raise it)."""


class BenchmarkError(ValueError):
    """Bad benchmark input; the message names the problem and the fix."""
