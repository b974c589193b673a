"""Attitude error budget of a star tracker (Sun et al., Sensors 2013) and of the IMU system.

:mod:`.propagation` holds the error model (linear, with analytic Jacobians, and exact for
Monte Carlo), :mod:`.sources` builds the error sources from a result file or a spec,
:mod:`.analysis` runs the budget, :mod:`.report` prints and plots it, :mod:`.command` is the
``stellar-cal budget`` subcommand.  The derivation is in ``doc/budget.md``.
"""
