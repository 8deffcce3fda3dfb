"""Optimal control on nhjax systems (gradient-based and Pontryagin).

Not implemented yet: this package is reserved for the optimal-control solvers
(issue #5). nhjax.simulate already accepts parametrized, differentiable
controls (``nhjax.Sinusoids``, ``nhjax.PiecewiseLinear``, ...), and
``jax.grad`` through simulate() works, which is what the direct methods here
will build on.
"""

__all__: list[str] = []
