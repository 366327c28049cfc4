"""Differentiable sparse solves and generalized eigenpairs for the operators of this package.

:mod:`.factor` (SuperLU and CHOLMOD factorizations, cached on the operator), :mod:`.solves`
(``solve``, ``dirichlet_solve``), :mod:`.derivatives` (eigenvalue and eigenvector
derivatives), :mod:`.eigenpairs` (``eigs`` and its measured route rule).
"""

from .eigenpairs import eigs
from .eigenpairs import eigs_route as eigs_route
from .factor import CholeskyFactorization as CholeskyFactorization
from .factor import Factorization as Factorization
from .factor import spd_splu as spd_splu
from .solves import ConvergenceError as ConvergenceError
from .solves import dirichlet_solve, solve

__all__ = ["solve", "dirichlet_solve", "eigs"]
