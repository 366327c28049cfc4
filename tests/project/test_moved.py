"""``moved``: the topology's layouts reach another device whole, field by field."""

import dataclasses

import torch

import torch_polylap as tp
from torch_polylap.assembly import gather_plan_of
from torch_polylap.moved import moved
from torch_polylap.shapes import quad_grid

META = torch.device("meta")


def _tensors(obj: object) -> list[torch.Tensor]:
    """Every tensor reachable through dataclass fields and tuples."""
    if isinstance(obj, torch.Tensor):
        return [obj]
    if dataclasses.is_dataclass(obj):
        return [t for f in dataclasses.fields(obj) for t in _tensors(getattr(obj, f.name))]
    if isinstance(obj, tuple):
        return [t for v in obj for t in _tensors(v)]
    return []


def test_groups_and_plan_move_every_tensor_and_keep_the_rest() -> None:
    V, F = quad_grid(3, bump=0.1)
    topo = tp.build_topology(F, V.shape[0])
    view = topo.on(V.device)
    plan = gather_plan_of(topo, view)
    for layout in (*view.groups, *view.groups[0].chunks, plan, plan.vertex):
        out = layout.to(META)
        assert type(out) is type(layout)
        before, after = _tensors(layout), _tensors(out)
        assert len(after) == len(before) > 0
        for a, b in zip(before, after, strict=True):
            assert b.device == META and a.device.type == "cpu"
            assert (a.shape, a.dtype) == (b.shape, b.dtype)
        for f in dataclasses.fields(layout):
            value = getattr(layout, f.name)
            if isinstance(value, int):
                assert getattr(out, f.name) == value


def test_moved_leaves_the_original_alone() -> None:
    V, F = quad_grid(2)
    group = tp.build_topology(F, V.shape[0]).on(V.device).groups[0]
    out = moved(group, META)
    assert group.face_ids.device.type == "cpu" and out.face_ids.device == META
