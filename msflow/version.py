"""msflow's version (its own module, so that records can name it without importing the package API)."""

__version__ = "0.1.0"
