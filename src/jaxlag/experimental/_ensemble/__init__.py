"""Private: no public API here (see jaxlag/experimental/__init__.py)."""
