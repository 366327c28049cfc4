"""A frozen dataclass of index tensors moved to another device, field by field."""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import torch

__all__ = ["moved"]

T = TypeVar("T")


def moved(obj: T, device: torch.device) -> T:
    """A copy of the dataclass ``obj`` whose tensor fields are on ``device``; fields that are
    dataclasses, or tuples of them, are moved the same way, the others kept (sizes, ranges).
    The topology's layouts (degree groups, gather plans) are computed once on the CPU and
    moved whole to each device they are used on."""
    changes = {
        field.name: _moved_value(getattr(obj, field.name), device)
        for field in dataclasses.fields(obj)  # type: ignore[arg-type]
    }
    return dataclasses.replace(obj, **changes)  # type: ignore[type-var]


def _moved_value(value: Any, device: torch.device) -> Any:
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return moved(value, device)
    if isinstance(value, tuple):
        return tuple(_moved_value(v, device) for v in value)
    return value
