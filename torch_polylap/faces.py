"""Polygon faces in packed form, and conversion from every form a user has.

A polygon mesh with faces of mixed degree is stored the way pytorch3d packs heterogeneous
data: one flat index tensor holding every face's vertices in order, plus an offsets tensor
(``offsets[f]:offsets[f + 1]`` are the corners of face ``f``).  Uniform meshes, lists of
Python sequences and numpy arrays all convert to this one form through :func:`as_faces`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch

from .tracing import tracing

__all__ = ["PolygonFaces", "as_faces", "FacesLike"]


class PolygonFaces:
    """Packed polygon faces: flat vertex indices plus per-face offsets.

    Args:
        indices: ``(N,)`` integer tensor, the corners of all faces concatenated, each face in
            its cyclic order (counter-clockwise seen from outside for consistent orientation).
        sizes: ``(F,)`` number of corners of each face. Give ``sizes`` or ``offsets``.
        offsets: ``(F + 1,)`` start of each face in ``indices``; ``offsets[-1] == N``.

    Only the index arrays are stored (int64, CPU unless moved with :meth:`to`); geometry lives
    in a separate ``verts`` tensor, so one ``PolygonFaces`` serves many vertex positions. The
    corner maps (:attr:`corner_face`, :attr:`next_corner`, :attr:`prev_corner`) are computed
    on first use and kept: treat the index tensors as read-only.
    """

    __slots__ = ("indices", "offsets", "_sizes", "_corner_face", "_corner_cycle")

    def __init__(
        self,
        indices: torch.Tensor | np.ndarray | Sequence[int],
        sizes: torch.Tensor | np.ndarray | Sequence[int] | None = None,
        offsets: torch.Tensor | np.ndarray | Sequence[int] | None = None,
    ) -> None:
        idx = _as_index_tensor(indices, "indices")
        if (sizes is None) == (offsets is None):
            raise ValueError("PolygonFaces needs exactly one of `sizes` or `offsets`.")
        if sizes is not None:
            sz = _as_index_tensor(sizes, "sizes").to(idx.device)
            off = torch.zeros(sz.numel() + 1, dtype=torch.int64, device=idx.device)
            torch.cumsum(sz, 0, out=off[1:])
        else:
            off = _as_index_tensor(offsets, "offsets").to(idx.device)
            if off.numel() == 0 or int(off[0]) != 0:
                raise ValueError("`offsets` must start with 0 and have length F + 1.")
            sz = off.diff()
        if int(off[-1]) != idx.numel():
            raise ValueError(
                f"face sizes add up to {int(off[-1])} corners but `indices` holds {idx.numel()}."
            )
        if sz.numel() and int(sz.min()) < 3:
            bad = int(torch.nonzero(sz < 3)[0, 0])
            raise ValueError(
                f"face {bad} has {int(sz[bad])} vertices; a polygon needs at least 3. "
                "Remove degenerate faces (points and line segments) before building a Laplacian."
            )
        self.indices = idx
        self.offsets = off
        self._sizes = sz
        self._corner_face: torch.Tensor | None = None
        self._corner_cycle: tuple[torch.Tensor, torch.Tensor] | None = None

    @property
    def sizes(self) -> torch.Tensor:
        """``(F,)`` number of corners (the degree) of each face."""
        return self._sizes

    @property
    def num_faces(self) -> int:
        return self._sizes.numel()

    @property
    def num_corners(self) -> int:
        """Total number of face corners, which is also the number of half-edges."""
        return self.indices.numel()

    @property
    def device(self) -> torch.device:
        return self.indices.device

    def __len__(self) -> int:
        return self.num_faces

    def __getitem__(self, f: int) -> torch.Tensor:
        """The vertex indices of face ``f`` in cyclic order."""
        if not -self.num_faces <= f < self.num_faces:
            raise IndexError(f"face {f} is out of range for {self.num_faces} faces")
        f = f % self.num_faces
        return self.indices[int(self.offsets[f]) : int(self.offsets[f + 1])]

    def __repr__(self) -> str:
        degrees = torch.unique(self._sizes.cpu()).tolist()
        return f"PolygonFaces(num_faces={self.num_faces}, degrees={degrees})"

    def to(self, device: torch.device | str) -> PolygonFaces:
        out = PolygonFaces.__new__(PolygonFaces)
        out.indices = self.indices.to(device)
        out.offsets = self.offsets.to(device)
        out._sizes = self._sizes.to(device)
        out._corner_face = out._corner_cycle = None
        return out

    def tolist(self) -> list[list[int]]:
        """Faces as a list of Python lists (handy for small meshes and printing)."""
        flat = self.indices.cpu().tolist()
        off = self.offsets.cpu().tolist()
        return [flat[off[f] : off[f + 1]] for f in range(self.num_faces)]

    def as_uniform(self) -> torch.Tensor | None:
        """``(F, k)`` index tensor when every face has the same degree ``k``, else ``None``."""
        if self.num_faces == 0:
            return None
        k = int(self._sizes[0])
        if not bool((self._sizes == k).all()):
            return None
        return self.indices.view(self.num_faces, k)

    @property
    def corner_face(self) -> torch.Tensor:
        """``(N,)`` the face each packed corner belongs to (computed once, then kept)."""
        face = self._corner_face
        if face is None:
            face = torch.repeat_interleave(
                torch.arange(self.num_faces, device=self.device), self._sizes
            )
            if not tracing():  # a traced value must not outlive its graph
                self._corner_face = face
        return face

    @property
    def next_corner(self) -> torch.Tensor:
        """``(N,)`` the packed position of the next corner within the same face, in cyclic
        order (the last corner of a face is followed by its first): half-edge ``c`` runs from
        vertex ``indices[c]`` to ``indices[next_corner[c]]``."""
        return self._cycle()[0]

    @property
    def prev_corner(self) -> torch.Tensor:
        """``(N,)`` the packed position of the previous corner within the same face (the
        inverse permutation of :attr:`next_corner`)."""
        return self._cycle()[1]

    def _cycle(self) -> tuple[torch.Tensor, torch.Tensor]:
        cycle = self._corner_cycle
        if cycle is None:
            if self.device.type == "cpu" and not tracing():
                cycle = _corner_cycle_numpy(self.offsets.numpy())
            else:
                n = self.num_corners
                nxt = torch.arange(1, n + 1, device=self.device)
                prv = torch.arange(-1, n - 1, device=self.device)
                first, last = self.offsets[:-1], self.offsets[1:] - 1
                nxt[last] = first
                prv[first] = last
                cycle = (nxt, prv)
            if not tracing():
                self._corner_cycle = cycle
        return cycle

    def flipped(self) -> PolygonFaces:
        """The same faces with reversed orientation (corner order reversed within each face)."""
        face = self.corner_face
        start, end = self.offsets[:-1][face], self.offsets[1:][face]
        pos = torch.arange(self.num_corners, device=self.device)
        return PolygonFaces(self.indices[start + end - 1 - pos], sizes=self._sizes)


def _corner_cycle_numpy(offsets: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """``(next, prev)`` corner maps, each ``(N,)`` int64, from ``(F + 1,)`` CPU offsets.

    numpy rather than torch on the CPU: numpy asks the kernel for huge pages on large arrays,
    and at millions of corners first touching fresh 4 KiB pages costs more than the arithmetic.
    """
    n = int(offsets[-1])
    nxt = np.arange(1, n + 1, dtype=np.int64)
    prv = np.arange(-1, n - 1, dtype=np.int64)
    nxt[offsets[1:] - 1] = offsets[:-1]
    prv[offsets[:-1]] = offsets[1:] - 1
    return torch.from_numpy(nxt), torch.from_numpy(prv)


FacesLike = PolygonFaces | torch.Tensor | np.ndarray | Sequence[Sequence[int]]


def _as_index_tensor(x: object, name: str, k: int | None = None) -> torch.Tensor:
    """``x`` as a flat int64 tensor of indices.

    Floating-point input is accepted only where every value is an integer (text loaders such
    as ``np.loadtxt`` return float64 faces); a fractional, NaN or infinite value is refused,
    naming the entry (and its face, when the faces have a uniform degree ``k``), never
    truncated to a different vertex.
    """
    t = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))
    if t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"`{name}` must hold integer vertex indices, got dtype {t.dtype}.")
    if t.is_floating_point():
        flat = t.reshape(-1)
        fractional = ~torch.isfinite(flat) | (flat != flat.round())
        if bool(fractional.any()):
            i = int(torch.nonzero(fractional)[0, 0])
            where = f"face {i // k} (entry {i})" if k else f"{name}[{i}]"
            raise ValueError(
                f"`{name}` must hold integer vertex indices: {where} is {flat[i].item()!r} "
                f"(dtype {t.dtype}); a fractional index would silently be truncated to another "
                "vertex. Fix the faces (integer-valued floats are accepted)."
            )
    return t.reshape(-1).to(torch.int64)


def as_faces(faces: FacesLike) -> PolygonFaces:
    """Convert faces in any accepted form to :class:`PolygonFaces`.

    Accepted forms:
        * :class:`PolygonFaces` (returned as is);
        * an ``(F, k)`` integer tensor or numpy array (uniform degree ``k >= 3``);
        * a sequence of index sequences of mixed length, e.g. ``[[0, 1, 2, 3], [3, 2, 4]]``;
        * a ``(indices, sizes)`` pair is *not* guessed: build ``PolygonFaces(indices, sizes=...)``.

    Examples:
        >>> import torch_polylap as tp
        >>> faces = tp.as_faces([[0, 1, 2, 3], [3, 2, 4]])
        >>> faces
        PolygonFaces(num_faces=2, degrees=[3, 4])
        >>> faces.sizes.tolist(), faces.offsets.tolist()
        ([4, 3], [0, 4, 7])
        >>> faces[1].tolist()
        [3, 2, 4]
    """
    if isinstance(faces, PolygonFaces):
        return faces
    if isinstance(faces, (torch.Tensor, np.ndarray)):
        if faces.ndim != 2:
            raise ValueError(
                f"face array must have shape (F, k), got {tuple(faces.shape)}; for faces of mixed "
                "degree pass a list of index lists or PolygonFaces(indices, sizes=...)."
            )
        f, k = faces.shape
        t = _as_index_tensor(faces, "faces", k)
        return PolygonFaces(t, sizes=torch.full((f,), k, dtype=torch.int64, device=t.device))
    if isinstance(faces, Sequence) and not isinstance(faces, (str, bytes)):
        sizes = []
        flat: list = []
        for i, face in enumerate(faces):  # a ragged list has to be walked once
            if isinstance(face, (str, bytes)) or not isinstance(face, Iterable):
                raise ValueError(
                    f"face {i} is {face!r}; each face must be a sequence of vertex indices."
                )
            face_list = list(face)
            sizes.append(len(face_list))
            flat.extend(face_list)
        return PolygonFaces(
            _flat_indices(flat, sizes), sizes=torch.tensor(sizes, dtype=torch.int64)
        )
    raise ValueError(
        f"cannot interpret faces of type {type(faces).__name__}; pass an (F, k) integer "
        "tensor/array, a list of index lists, or PolygonFaces."
    )


def _flat_indices(flat: list, sizes: list[int]) -> torch.Tensor:
    """The concatenated corners of a list of faces as int64, refusing (and naming the face
    of) the first entry that is not an integer index."""
    arr = np.asarray(flat)
    if arr.size == 0:
        return torch.zeros(0, dtype=torch.int64)
    if arr.dtype.kind not in "iuf":
        bad = next(i for i, v in enumerate(flat) if not isinstance(v, (int, np.integer, float)))
        face = int(np.searchsorted(np.cumsum(sizes), bad, side="right"))
        raise ValueError(
            f"face {face} holds {flat[bad]!r}; each face must be a sequence of vertex indices."
        )
    if arr.dtype.kind == "f":
        fractional = ~np.isfinite(arr) | (arr != np.round(arr))
        if fractional.any():
            bad = int(np.flatnonzero(fractional)[0])
            face = int(np.searchsorted(np.cumsum(sizes), bad, side="right"))
            raise ValueError(
                f"face {face} holds the vertex index {flat[bad]!r}, which is not an integer; a "
                "fractional index would silently be truncated to another vertex. Fix the faces "
                "(integer-valued floats are accepted)."
            )
    return torch.from_numpy(arr.astype(np.int64))
