"""The version of dampax (one place; the package, the CLI and file metadata read it)."""

__version__ = "0.1.0"
