"""magrun: controlled experiments with magnetic micro-robots under fluoroscopy-like feedback.

Implements "Fluoroscopy-Constrained Magnetic Robot Control via Zernike-Based Field Modeling
and Nonlinear MPC". Subpackages:

- :mod:`magrun.field` — coil system, reference (FEA-like) field maps, Zernike and
  lookup-table field models with analytic gradients (NumPy and CasADi).

Command line: ``magrun --help``.
"""

__version__ = "0.1.0"
