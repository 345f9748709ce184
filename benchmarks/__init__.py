"""jaxlag performance benchmarks: ``python -m benchmarks`` from the repository root."""
