"""Differentiable sparse solves and generalized eigenpairs for the operators of this package.

:mod:`.factor` (SuperLU, CHOLMOD and QDLDL factorizations, cached on the operator),
:mod:`.etree_solve` (solves from few sources over elimination-tree paths),
:mod:`.hermitian` (complex Hermitian ``L D L^H`` for the vector heat method), :mod:`.cg`
(conjugate gradients), :mod:`.solve_op` (the solve as a ``torch.library`` operator),
:mod:`.solves` (``solve``, ``dirichlet_solve``), :mod:`.derivatives` (eigenvalue and
eigenvector derivatives), :mod:`.lanczos` (block Lanczos), :mod:`.eigenpairs` (``eigs`` and
its measured route rule).  The rest of the package imports from here, never from the modules.
"""

from .cg import ConvergenceError as ConvergenceError
from .derivatives import top_eigenpair as top_eigenpair
from .eigenpairs import eigenpair_gradients as eigenpair_gradients
from .eigenpairs import eigs
from .eigenpairs import eigs_route as eigs_route
from .factor import CholeskyFactorization as CholeskyFactorization
from .factor import Factor as Factor
from .factor import Factorization as Factorization
from .factor import IllConditionedWarning as IllConditionedWarning
from .factor import LDLFactorization as LDLFactorization
from .factor import cached_factorization as cached_factorization
from .factor import cholespy_available as cholespy_available
from .factor import qdldl_available as qdldl_available
from .factor import spd_splu as spd_splu
from .hermitian import HermitianLDL as HermitianLDL
from .solves import dirichlet_solve, solve

__all__ = ["solve", "dirichlet_solve", "eigs", "IllConditionedWarning"]
