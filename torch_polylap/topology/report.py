"""What keeps a mesh from being a consistently oriented 2-manifold, and how it is announced."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# How many of the first offending elements the warning and the error messages list.
_SHOW = 5


@dataclass(frozen=True)
class TopologyReport:
    """What a mesh has that a consistently oriented 2-manifold would not.

    None of it changes ``L`` or ``M0``; it matters to what needs a manifold or an orientation
    (half-edge twins, boundary loops, normals of neighbouring faces).  All arrays are numpy
    int64 and sorted.

    Attributes:
        non_manifold_edges: ``(n, 2)`` vertex pairs ``p < q`` used as an edge by 3+ faces.
        non_manifold_vertices: ``(n,)`` vertices whose faces do not form one fan (two cones
            touching at their tips, two sheets sharing one vertex), plus the endpoints of
            non-manifold edges.
        misoriented_edges: ``(n, 2)`` edges ``(p, q)`` whose two faces both traverse
            ``p -> q`` (one of them is flipped relative to the other).
        non_orientable_components: number of components (faces connected through edges used
            by two faces) that admit no consistent orientation, e.g. a Moebius band. Searched
            only when misoriented edges exist (an oriented mesh is orientable).
        duplicate_faces: ``(n,)`` faces repeating the vertex cycle of an earlier face, up to
            rotation and reflection. Searched only when the mesh has non-manifold or
            misoriented edges, which every duplicate creates except one: a lone face and its
            reverse, a closed two-face "pillow", which is a valid manifold.
        isolated_vertices: ``(n,)`` vertices used by no face (zero mass, empty rows of ``L``).
    """

    non_manifold_edges: np.ndarray
    non_manifold_vertices: np.ndarray
    misoriented_edges: np.ndarray
    non_orientable_components: int
    duplicate_faces: np.ndarray
    isolated_vertices: np.ndarray

    @property
    def is_manifold(self) -> bool:
        """No non-manifold edge or vertex."""
        return self.non_manifold_edges.size == 0 and self.non_manifold_vertices.size == 0

    @property
    def is_oriented(self) -> bool:
        """Every edge used by two faces is traversed in opposite directions."""
        return self.misoriented_edges.size == 0

    @property
    def is_clean(self) -> bool:
        """Manifold, oriented, no duplicated face, no isolated vertex."""
        return (
            self.is_manifold
            and self.is_oriented
            and self.duplicate_faces.size == 0
            and self.isolated_vertices.size == 0
        )

    def lines(self, num_verts: int | None = None) -> list[str]:
        """One line per finding: what, how many, the first few by index."""
        out = []
        if self.non_manifold_edges.size:
            out.append(
                f"{len(self.non_manifold_edges)} non-manifold edge(s) used by 3+ faces "
                f"(first: {_first(self.non_manifold_edges)})"
            )
        if self.non_manifold_vertices.size:
            out.append(
                f"{self.non_manifold_vertices.size} non-manifold vertex(es) "
                f"(first: {_first(self.non_manifold_vertices)})"
            )
        if self.misoriented_edges.size:
            out.append(
                f"{len(self.misoriented_edges)} edge(s) traversed in the same direction by both "
                f"faces, i.e. inconsistent orientation (first: {_first(self.misoriented_edges)})"
            )
        if self.non_orientable_components:
            out.append(
                f"{self.non_orientable_components} non-orientable component(s) "
                "(e.g. a Moebius band)"
            )
        if self.duplicate_faces.size:
            out.append(
                f"{self.duplicate_faces.size} duplicated face(s) (first: "
                f"{_first(self.duplicate_faces)})"
            )
        if self.isolated_vertices.size:
            of = "" if num_verts is None else f" of {num_verts}"
            out.append(
                f"{self.isolated_vertices.size}{of} vertices belong to no face "
                f"(first: {_first(self.isolated_vertices)}); they get zero mass and empty rows "
                "in L"
            )
        return out

    def summary(self, num_verts: int | None = None) -> str:
        """The findings in one paragraph (empty for a clean mesh)."""
        return "; ".join(self.lines(num_verts))


def _first(a: np.ndarray) -> list:
    return a[:_SHOW].tolist()
