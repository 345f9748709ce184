"""Private: no public API here (see jaxlag/__init__.py)."""
