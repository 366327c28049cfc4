"""One vocabulary for validating user input, modelled on kornia's ``kornia/core/check.py``.

Every ``check_*`` function either returns (a normalized form of) its argument or raises a
:class:`TypeError` (wrong kind of object) or :class:`ValueError` (right kind, bad content)
whose message names the argument, the first offending element and what to do about it.
Entry points call them first thing, so a bad input fails at the call that received it, not
deep inside an assembly loop.

    >>> from torch_polylap.checks import check_verts, check_lam
    >>> check_lam(-1.0)
    Traceback (most recent call last):
    ...
    ValueError: lam must be a finite number >= 0, got -1.0; ...
"""

from __future__ import annotations

import math
import numbers
import os
import sys
import types
import warnings

import numpy as np
import torch

from .tracing import require

__all__ = [
    "check_verts",
    "check_verts_array",
    "check_lam",
    "check_lam_tensor_shape",
    "check_index_or_mask",
    "check_int",
    "check_positive_int",
    "NotAnIntegerError",
    "inverse_or_zero",
    "check_finite",
    "check_finite_operand",
    "Lam",
    "warn_outside_package",
    "Float32PrecisionWarning",
]

# The stabilizer weight's type: a float, or a 0-dim tensor that may carry a gradient.
Lam = float | torch.Tensor

# Half precision cannot hold the products the per-face formulas form (squared lengths of a
# unit-size face times a 1e-3 relative spacing already underflow float16), and the sparse
# kernels L and M0 feed into have no half-precision CPU implementation. Refusing is clearer
# than a silent upcast that would hand back a matrix of a different dtype.
_SUPPORTED_FLOATS = (torch.float32, torch.float64)


def check_verts(verts: object, name: str = "verts", *, finite: bool = True) -> torch.Tensor:
    """``verts`` must be a ``(V, 3)`` float32/float64 tensor with finite entries.

    ``finite=False`` skips the finiteness test (it costs one reduction and a device sync; the
    assembly's own ``validate`` pass can do it later at no extra sync).

    Returns:
        ``verts`` unchanged, or in float32 when it is half precision under ``torch.autocast``.

    Raises:
        TypeError: not a tensor, or not floating point, or half precision outside autocast
            (float16/bfloat16 are refused: convert with ``verts.float()`` and cast the results
            back).
        ValueError: wrong shape, or a non-finite entry (names the first vertex).
    """
    if not isinstance(verts, torch.Tensor):
        raise TypeError(
            f"{name} must be a torch.Tensor of shape (V, 3), got {type(verts).__name__}."
        )
    if verts.dim() != 2 or verts.shape[1] != 3:
        raise ValueError(f"{name} must have shape (V, 3), got {tuple(verts.shape)}.")
    if verts.dtype in (torch.float16, torch.bfloat16) and torch.is_autocast_enabled(
        verts.device.type
    ):
        # under autocast, half-precision positions (a network's output) are taken in float32,
        # as autocast does for its float32 ops; the gradient flows back through the cast
        verts = verts.float()
    if verts.dtype not in _SUPPORTED_FLOATS:
        hint = (
            f"use {name}.float() and cast the results back"
            if verts.is_floating_point()
            else f"use {name}.double()"
        )
        raise TypeError(
            f"{name} must be floating point (float32 or float64), got {verts.dtype}; {hint}."
        )
    if finite:
        check_finite(verts, name, what="vertex")
    return verts


def check_verts_array(verts: object, name: str = "verts") -> np.ndarray:
    """``verts`` as a ``(V, 3)`` float64 numpy array, for the numpy-side entries (writers,
    repairs, figures) that accept arrays as well as tensors (detached and copied to the CPU).

    Raises:
        TypeError: not numeric (strings, objects, complex numbers).
        ValueError: wrong shape.
    """
    if isinstance(verts, torch.Tensor):
        if verts.is_complex() or verts.dtype == torch.bool:
            raise TypeError(f"{name} must hold real coordinates, got dtype {verts.dtype}.")
        arr = verts.detach().cpu().to(torch.float64).numpy()
    else:
        arr = np.asarray(verts)
    if arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must hold real coordinates, got {arr.dtype} values.")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (V, 3), got {tuple(arr.shape)}.")
    return arr.astype(np.float64, copy=False)


def check_finite(x: torch.Tensor, name: str, what: str = "row") -> None:
    """Raise a ValueError naming the first row of ``x`` that holds a NaN or an infinity.

    One reduction and one host sync when everything is finite. Traced (torch.compile) or
    under vmap, an in-graph assertion instead (:func:`~torch_polylap.tracing.require`), whose
    message names the tensor but not the row.
    """
    finite = torch.isfinite(x)
    if require(finite, f"{name} holds a NaN or an infinity; fix it before building operators."):
        return
    bad = ~finite.reshape(x.shape[0], -1).all(1) if x.dim() else ~finite.reshape(1)
    first = int(torch.nonzero(bad)[0, 0])
    value = x[first].tolist() if x.dim() else x.item()
    raise ValueError(
        f"{what} {first} of {name} is not finite ({value}; {int(bad.sum())} such {what}(s)); "
        f"fix or remove it before building operators."
    )


def check_lam(lam: object, name: str = "lam") -> Lam:
    """The stabilizer weight: a finite number ``>= 0`` (0 keeps only the geometric part).

    Accepts a Python/numpy real number or a 0-dim (or one-element) floating tensor, which is
    returned as is so that it can carry a gradient. Reading a tensor's value syncs once.

    Raises:
        TypeError: not a real number (e.g. a string, a complex number, a bool, a vector).
        ValueError: NaN, infinite or negative.
    """
    if isinstance(lam, torch.Tensor):
        check_lam_tensor_shape(lam, name)
        value = float(lam.detach())
    elif isinstance(lam, numbers.Real) and not isinstance(lam, (bool, np.bool_)):
        value = float(lam)
    else:
        raise TypeError(f"{name} must be a real number, got {type(lam).__name__} {lam!r}.")
    # comparisons rather than math.isfinite: torch.compile with dynamic shapes may trace a
    # number as a symbol, which math.isfinite cannot take (NaN fails both comparisons)
    if not 0 <= value < math.inf:
        raise ValueError(
            f"{name} must be a finite number >= 0, got {value}; the stabilizer weight lambda of "
            "AW11 eq. 9 is usually between 1 and 3 (0 keeps only the geometric part)."
        )
    return lam if isinstance(lam, torch.Tensor) else value


def check_lam_tensor_shape(lam: torch.Tensor, name: str = "lam") -> None:
    """A tensor ``lam`` must hold one floating value (checked without reading it)."""
    if lam.numel() != 1 or not lam.is_floating_point():
        raise TypeError(
            f"{name} must be a real number or a 0-dim floating tensor, got a tensor of "
            f"shape {tuple(lam.shape)} and dtype {lam.dtype}."
        )


class NotAnIntegerError(TypeError, ValueError):
    """A count or index that is not an integer (a bool, a float such as ``2.0``, a string).

    A :class:`TypeError` (wrong kind of object), and a :class:`ValueError` too: some entries
    refused such values with a ValueError before their checks were shared, and code that
    catches that keeps working."""


def check_int(value: object, name: str, *, least: int = 1) -> int:
    """``value`` must be a Python or numpy integer ``>= least`` (not a bool, not a float like
    ``2.0``); returned as an ``int``.

    Raises:
        NotAnIntegerError: not an integer (a :class:`TypeError` and a :class:`ValueError`).
        ValueError: an integer below ``least``.
    """
    wanted = "a positive integer" if least == 1 else f"an integer >= {least}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise NotAnIntegerError(
            f"{name} must be {wanted}, got {type(value).__name__} {value!r}; "
            f"pass int({name}) if the value is integral."
        )
    if value < least:
        raise ValueError(f"{name} must be {wanted}, got {int(value)}.")
    return int(value)


def check_positive_int(k: object, name: str) -> int:
    """``k`` must be a Python or numpy integer ``>= 1``: :func:`check_int` with ``least=1``."""
    return check_int(k, name, least=1)


def check_index_or_mask(x: object, n: int, name: str) -> torch.Tensor:
    """Indices into ``range(n)`` or a length-``n`` boolean mask, as int64 indices.

    Args:
        x: a bool mask of shape ``(n,)``, or integer indices (tensor, array or sequence), each
            in ``[0, n)``; negative indices are refused (a mesh index never counts from the
            end, so a negative one is a bug upstream).
        n: the size of the indexed dimension (e.g. the number of vertices).
        name: the argument's name in messages.

    Returns:
        ``(m,)`` int64 indices on the input's device (CPU for non-tensors).

    Raises:
        TypeError: floating or complex indices (name the first one), or an unusable object.
        ValueError: a mask of the wrong length, an index out of range, or a repeated index
            (each names the first offending entry).
    """
    t = x if isinstance(x, torch.Tensor) else _as_tensor(x, name)
    if t.dtype == torch.bool:
        if t.dim() != 1 or t.numel() != n:
            raise ValueError(
                f"{name} is a boolean mask of shape {tuple(t.shape)}, but it must have shape "
                f"({n},), one entry per element."
            )
        return torch.nonzero(t).reshape(-1)
    if t.is_floating_point() or t.is_complex():
        first = t.reshape(-1)[0].item() if t.numel() else None
        raise TypeError(
            f"{name} must hold integer indices or be a boolean mask, got dtype {t.dtype} "
            f"(first entry {first!r}); convert integral values with .long()."
        )
    if t.dim() > 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {tuple(t.shape)}.")
    idx = t.reshape(-1).to(torch.int64)
    bad = (idx < 0) | (idx >= n)
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0, 0])
        raise ValueError(
            f"{name}[{i}] = {int(idx[i])} is out of range for {n} elements (valid: 0..{n - 1}); "
            "negative indices are not accepted."
        )
    if idx.numel() > 1:
        order = torch.sort(idx, stable=True)
        repeat = order.values[1:] == order.values[:-1]
        if bool(repeat.any()):
            j = int(torch.nonzero(repeat)[0, 0])
            i = int(order.indices[j + 1])
            raise ValueError(
                f"{name}[{i}] = {int(idx[i])} repeats an earlier index; pass each index once "
                f"(e.g. torch.unique({name}))."
            )
    return idx


def _as_tensor(x: object, name: str) -> torch.Tensor:
    try:
        arr = np.asarray(x)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be indices or a boolean mask: {err}") from None
    if arr.dtype == object:
        raise TypeError(
            f"{name} must be indices or a boolean mask, got an object array from "
            f"{type(x).__name__}."
        )
    if arr.size == 0:
        # numpy gives an empty list the dtype float64; no index is an index list all the same
        arr = arr.astype(np.int64)
    return torch.from_numpy(np.ascontiguousarray(arr))


def inverse_or_zero(d: torch.Tensor) -> torch.Tensor:
    """``1 / d`` where ``d > 0``, else 0, elementwise (any shape): the inverse of a lumped mass
    (or of a Laplacian's diagonal) with the rows of isolated vertices, whose mass is zero, set
    to zero rather than divided by zero. Differentiable where ``d > 0`` (no NaN gradient from
    the other branch)."""
    pos = d > 0
    return torch.where(pos, 1.0 / torch.where(pos, d, torch.ones_like(d)), torch.zeros_like(d))


class Float32PrecisionWarning(UserWarning):
    """float32 operators whose products lose more than about ``1e-2`` relative accuracy.

    Raised once per call by :func:`~torch_polylap.laplacian` (and the batched, module and
    :class:`~torch_polylap.CompiledLaplacian` forms) when float32 vertices have a face so thin
    that ``L @ X`` and the gradients through it are expected to lose that much: the message
    names the worst face and the digits lost. Use float64 vertices for such meshes, or repair
    the face (:mod:`torch_polylap.repair`). Never raised in float64.
    """


def warn_outside_package(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` of ``category`` attributed to the first caller outside torch_polylap."""
    package = os.path.dirname(os.path.abspath(__file__))
    level = 2  # the caller of this helper
    frame: types.FrameType | None = sys._getframe(1)
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        level += 1
        frame = frame.f_back
    warnings.warn(message, category, stacklevel=level)


def check_finite_operand(A: torch.Tensor, name: str, caller: str) -> None:
    """Raise a ValueError naming the first NaN or infinite entry of ``A`` (row, column, value),
    an operand of a linear-algebra call (``solve``, ``eigs``): checked before anything else,
    so that a NaN is not reported as an asymmetry or a singular matrix.

    Args:
        A: a sparse operator of this package ``(n, m)`` (its stored entries are checked), or a
            dense ``(n,)`` or ``(n, c)`` tensor.
        name: the argument's name in the message (``"L"``, ``"B"``).
        caller: the function that received it.

    One reduction and one host sync when every entry is finite. Traced (torch.compile) or
    under vmap, an in-graph assertion instead (:func:`~torch_polylap.tracing.require`), whose
    message names the operand but not the entry.
    """
    from .sparse import is_operator
    from .sparse.construct import csr_indices, sparse_values

    sparse = is_operator(A)
    values = sparse_values(A) if sparse else A
    finite = torch.isfinite(values)
    if require(finite, f"{caller}: {name} holds a NaN or an infinity."):
        return
    bad = torch.nonzero(~finite.reshape(-1))[:, 0]
    first = int(bad[0])
    if sparse:
        crow, col = csr_indices(A)
        row = int(torch.searchsorted(crow, first, right=True)) - 1
        where = f"{name}[{row}, {int(col[first])}]"
    elif values.dim() == 2:
        where = f"{name}[{first // values.shape[1]}, {first % values.shape[1]}]"
    else:
        where = f"{name}[{first}]"
    raise ValueError(
        f"{caller}: {name} holds non-finite values: {where} = "
        f"{values.reshape(-1)[first].item()} ({bad.numel()} such entries). Find where they "
        "came from (a NaN vertex coordinate, a division by zero, a diverged optimization) "
        "and fix them first."
    )
