"""Private: no public API here (see jaxlag/__init__.py).

System identification, one job per module: ``options`` (reparameterizations and the option
Modules), ``data`` (experiments and their checks), ``checks`` (the other arguments), ``model``
(free variables -> residuals, and their linearization), ``loops`` (the optimistix and optax
loops), ``statistics`` (covariance, what the data cannot determine, `FitResult`) and
``fit`` (the entry points)."""
