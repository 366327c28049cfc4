"""The package's one topology cache: :func:`get_topology` and its limits."""

from __future__ import annotations

import threading
import weakref
import zlib
from collections import OrderedDict

import torch

from .._torch_compat import disable_functorch, functorch_unwrapped, version_counter
from ..faces import FacesLike, PolygonFaces
from ..tracing import require, run_eagerly, tracing
from .build import build_topology
from .structure import Topology

# Index tensors up to this many elements get a CRC32 in the cache stamp (about 3 ms per 2^20
# int64 entries), which catches edits through a numpy array sharing their memory; larger ones
# rely on the tensor version counter alone (see get_topology).
CHECKSUM_MAX_ELEMENTS = 1 << 20


class _TopologyCache:
    """Topologies keyed by the faces tensor they were built from, bounded in entries and bytes.

    Keys are ``id(tensor)`` guarded by a weak reference: the cache never keeps a faces tensor
    alive (nor does the topology, which holds a private copy of the indices), and an entry
    goes when its tensor is garbage collected. Least recently used entries are evicted beyond
    ``max_entries`` or ``max_bytes`` (the newest entry always stays). The weakref callback only
    records the dead key; removal happens under the lock on the next access, so a callback
    fired by the garbage collector in the middle of an update cannot deadlock or corrupt it.
    """

    def __init__(self, max_entries: int = 64, max_bytes: int = 2 << 30) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._entries: OrderedDict[int, tuple[weakref.ref[torch.Tensor], tuple, Topology, int]] = (
            OrderedDict()
        )
        self._bytes = 0
        self._dead: list[tuple[int, weakref.ref[torch.Tensor]]] = []
        self._lock = threading.Lock()

    def get(self, holder: torch.Tensor, stamp: tuple) -> Topology | None:
        with self._lock:
            self._purge()
            entry = self._entries.get(id(holder))
            if entry is None or entry[0]() is not holder or entry[1] != stamp:
                return None
            self._entries.move_to_end(id(holder))
            return entry[2]

    def put(self, holder: torch.Tensor, stamp: tuple, topo: Topology) -> None:
        key = id(holder)
        ref = weakref.ref(holder, lambda r: self._dead.append((key, r)))
        size = topo.nbytes
        with self._lock:
            self._purge()
            self._remove(key)
            self._entries[key] = (ref, stamp, topo, size)
            self._bytes += size
            while len(self._entries) > 1 and (
                len(self._entries) > self.max_entries or self._bytes > self.max_bytes
            ):
                self._remove(next(iter(self._entries)))

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self._bytes = 0

    def __len__(self) -> int:
        with self._lock:
            self._purge()
            return len(self._entries)

    def _purge(self) -> None:
        while self._dead:
            key, ref = self._dead.pop()
            entry = self._entries.get(key)
            if entry is not None and entry[0] is ref:
                self._remove(key)

    def _remove(self, key: int) -> None:
        entry = self._entries.pop(key, None)
        if entry is not None:
            self._bytes -= entry[3]


_CACHE = _TopologyCache()


def set_topology_cache_limits(max_entries: int = 64, max_bytes: int = 2 << 30) -> None:
    """Bound the topology cache of :func:`get_topology` (defaults: 64 entries, 2 GiB)."""
    _CACHE.max_entries, _CACHE.max_bytes = int(max_entries), int(max_bytes)


def clear_topology_cache() -> None:
    """Drop every cached topology."""
    _CACHE.clear()


def _stamp(faces: object, holder: torch.Tensor, num_verts: int) -> tuple:
    """What must be unchanged for a cached topology to be reused."""
    parts: list = [num_verts, *_tensor_stamp(holder)]
    if isinstance(faces, PolygonFaces):
        parts += _tensor_stamp(faces.offsets)
    return tuple(parts)


def _tensor_stamp(t: torch.Tensor) -> tuple:
    # The version counter misses writes through a numpy array sharing the memory
    # (np_view = t.numpy(); np_view[0] = 5): a CRC32 of small CPU tensors catches them.
    crc = None
    if t.device.type == "cpu" and t.numel() <= CHECKSUM_MAX_ELEMENTS:
        crc = zlib.crc32(t.detach().contiguous().numpy().data)
    return (version_counter(t), t.data_ptr(), tuple(t.shape), t.stride(), t.dtype, t.device, crc)


def get_topology(faces: FacesLike | Topology, num_verts: int) -> Topology:
    """The :class:`Topology` of ``faces``, from the package's one cache where possible.

    A :class:`Topology` is used as is. For a ``PolygonFaces`` or an index tensor the topology
    is cached (keyed weakly on the tensor, see :class:`_TopologyCache`) and reused while the
    content is unchanged: same version counter, same storage, same shape and, for CPU tensors
    up to :data:`CHECKSUM_MAX_ELEMENTS` entries, the same CRC32. Larger tensors edited in place
    through a numpy array that shares their memory bypass the version counter and are not
    detected: edit them with torch operations, or pass a new tensor. Lists and numpy arrays
    are converted anew on every call: keep a ``PolygonFaces``, a tensor, a ``Topology`` or a
    :class:`~torch_polylap.PolygonLaplacian` for repeated use.
    """
    if isinstance(faces, Topology):
        if faces.num_verts != num_verts:
            raise ValueError(
                f"the topology was built for {faces.num_verts} vertices "
                f"but verts has {num_verts} rows."
            )
        return faces
    if tracing():
        topo = run_eagerly(_lookup, faces, int(num_verts))
        _require_traced_faces(faces, topo)
        return topo
    return _lookup(faces, num_verts)


def topology_of(faces: FacesLike | Topology, verts: torch.Tensor) -> Topology:
    """:func:`get_topology` for ``verts`` ``(..., V, 3)``: the vertex count read from ``verts``.

    Under torch.compile with dynamic shapes the count is symbolic while the graph is traced;
    given the tensor, the lookup reads it from the real vertices at trace time.
    """
    if tracing() and not isinstance(faces, Topology):
        topo = run_eagerly(_lookup_for, faces, verts)
        _require_traced_faces(faces, topo)
        return topo
    return get_topology(faces, verts.shape[-2])


def _lookup_for(faces: FacesLike, verts: torch.Tensor) -> Topology:
    return _lookup(faces, int(verts.shape[-2]))


def _lookup(faces: FacesLike, num_verts: int) -> Topology:
    if isinstance(faces, torch.Tensor):
        faces = _unwrapped(faces)
    elif isinstance(faces, PolygonFaces):
        indices, offsets = _unwrapped(faces.indices), _unwrapped(faces.offsets)
        if indices is not faces.indices or offsets is not faces.offsets:
            with disable_functorch():
                faces = PolygonFaces(indices, offsets=offsets)
    # the plain tensors are read on the host (stamp, build) with torch.func's layers paused
    with disable_functorch():
        return _lookup_plain(faces, num_verts)


def _lookup_plain(faces: FacesLike, num_verts: int) -> Topology:
    holder = faces.indices if isinstance(faces, PolygonFaces) else faces
    if not isinstance(holder, torch.Tensor):
        return build_topology(faces, num_verts)
    stamp = _stamp(faces, holder, num_verts)
    topo = _CACHE.get(holder, stamp)
    if topo is None:
        topo = build_topology(faces, num_verts)
        _CACHE.put(holder, stamp, topo)
    return topo


def _unwrapped(t: torch.Tensor) -> torch.Tensor:
    """The plain tensor under torch.func's wrappers: inside a transform, tensor arguments are
    wrapped (without storage), but connectivity is never differentiated, so its content is
    that of the plain tensor."""
    return functorch_unwrapped(t, _BATCHED_FACES)


_BATCHED_FACES = (
    "torch_polylap: the faces are batched by torch.func.vmap; one mesh's operators need one "
    "connectivity. vmap over the vertices with the faces passed unbatched (in_dims=None), or "
    "loop over meshes of different connectivity."
)


# Under torch.compile the faces' content is not known while the graph is traced, but the
# topology -- degree groups, pattern, scatter maps -- decides the graph's shape. So the lookup
# runs once at trace time on the real faces (run_eagerly), the topology enters the graph as a
# constant, and the graph checks on every call that it is given the same faces.

_CHANGED_FACES = (
    "torch_polylap: the faces passed to this compiled function differ from those it was traced "
    "with; torch.compile builds the mesh's topology into the graph. For connectivity that "
    "changes between calls, build the topology outside the compiled function "
    "(topo = torch_polylap.get_topology(faces, num_verts)) and pass it in place of the faces: "
    "torch.compile then guards on it."
)


def _require_traced_faces(faces: FacesLike, topo: Topology) -> None:
    """Insert into the traced graph a check that ``faces`` is what ``topo`` was built from."""
    if isinstance(faces, PolygonFaces):
        pairs = [(faces.indices, topo.faces.indices), (faces.offsets, topo.faces.offsets)]
    elif isinstance(faces, torch.Tensor):
        pairs = [(faces.reshape(-1), topo.faces.indices)]
    else:
        return  # lists and arrays are constants of the graph: torch.compile guards on them
    for given, built in pairs:
        if given.numel() != built.numel():
            raise ValueError(_CHANGED_FACES)
        expected = topo.on(given.device).face_indices if built is topo.faces.indices else built
        require((given.to(torch.int64) == expected.to(given.device)).all(), _CHANGED_FACES)
