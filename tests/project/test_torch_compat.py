"""Private torch APIs are touched in one module, ``torch_polylap._torch_compat``, and nowhere else.

An AST scan of every other module of the package looks for a private torch name (a part
with one leading underscore; dunders such as ``__version__`` are public) in four forms:

* an import of a private torch module or name (``import torch._dynamo``,
  ``from torch.utils._pytree import ...``, ``from torch import _C``);
* an attribute chain that starts at a name bound to torch or one of its modules
  (``torch._C.X``, ``forward_ad._current_level`` after ``from torch.autograd import forward_ad``);
* a private attribute of a tensor (``t._version``, ``A._nnz()``): any attribute whose name is
  a private attribute of ``torch.Tensor``, on any object but ``self`` and ``cls`` (a class's
  own attributes, such as a solver's cached ``self._grad``);
* a marker attribute that torch.compile reads off user functions (``_dynamo_*``,
  ``_torchdynamo_*``).

Docstrings and comments may name private APIs (what was checked with ``torch._dynamo.explain``);
only code counts.
"""

from __future__ import annotations

import ast

import pytest
import torch
from conftest import ROOT

PACKAGE = ROOT / "torch_polylap"
COMPAT = PACKAGE / "_torch_compat.py"

# private attributes of tensors, as torch defines them
TENSOR_PRIVATE = frozenset(
    name for name in dir(torch.Tensor) if name.startswith("_") and not name.endswith("__")
)
COMPILE_MARKERS = ("_dynamo", "_torchdynamo")


def _private(part: str) -> bool:
    return part.startswith("_") and not part.endswith("__")


def _chain(node: ast.expr) -> list[str] | None:
    """``["a", "b", "c"]`` for the expression ``a.b.c`` (None when it does not start at a name)."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return [node.id, *reversed(parts)]


def private_torch_uses(source: str) -> list[str]:
    """``"line N: what"`` for every private torch name that ``source`` references."""
    tree = ast.parse(source)
    torch_names: dict[str, str] = {}  # local name -> the torch module path it is bound to
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "torch" or alias.name.startswith("torch."):
                    if any(_private(p) for p in alias.name.split(".")):
                        found.append(f"line {node.lineno}: import {alias.name}")
                    local = alias.asname or alias.name.split(".")[0]
                    torch_names[local] = alias.name if alias.asname else "torch"
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "torch" or node.module.startswith("torch."):
                for alias in node.names:
                    path = f"{node.module}.{alias.name}"
                    if any(_private(p) for p in path.split(".")):
                        found.append(f"line {node.lineno}: from {node.module} import {alias.name}")
                    torch_names[alias.asname or alias.name] = path
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        chain = _chain(node)
        if chain is not None and chain[0] in torch_names and any(_private(p) for p in chain[1:]):
            found.append(f"line {node.lineno}: {'.'.join(chain)}")
        elif node.attr in TENSOR_PRIVATE and not (chain and chain[:1] in (["self"], ["cls"])):
            found.append(f"line {node.lineno}: a tensor's .{node.attr}")
        elif node.attr.startswith(COMPILE_MARKERS):
            found.append(f"line {node.lineno}: torch.compile's marker .{node.attr}")
    return sorted(set(found), key=lambda s: int(s.split(":")[0].split()[1]))


@pytest.mark.parametrize(
    "source",
    [
        "import torch._dynamo",
        "import torch.utils._pytree as pytree",
        "from torch.utils._python_dispatch import _disable_current_modes",
        "from torch import _C",
        "import torch\nx = torch._C.DisableTorchFunctionSubclass()",
        "import torch\nok = torch._dynamo.config.capture_dynamic_output_shape_ops",
        "from torch.autograd import forward_ad\nlevel = forward_ad._current_level",
        "import torch as th\nth._assert_async(c)",
        "def f(t):\n    return t._version",
        "def f(A):\n    return A._nnz()",
        "def f():\n    pass\nf._dynamo_marked_constant = True",
    ],
)
def test_the_scan_finds_every_form(source):
    assert private_torch_uses(source), source


def test_the_scan_leaves_public_names_and_own_attributes_alone():
    source = (
        '"""Checked with ``torch._dynamo.explain``."""\n'
        "import torch\n"
        "from torch.autograd import forward_ad\n"
        "x = torch.compiler.is_compiling() and torch.__version__\n"
        "with forward_ad.dual_level():\n"
        "    pass\n"
        "def f(A):\n"
        "    return A._vals, A._crow, A._solver_cache, A._pattern_key  # torch._C in a comment\n"
        "class Solver:\n"
        "    def grad(self):\n"
        "        return self._grad\n"
    )
    assert private_torch_uses(source) == []


def test_the_package_s_own_attributes_are_named_apart_from_torch_s():
    """The tensor rule would flag an attribute of the package that shares a name with a
    private attribute of torch.Tensor; the operator's own are not such names."""
    from torch_polylap.sparse import SparseOperator

    own = set(SparseOperator.__annotations__)
    assert {"_vals", "_crow", "_col", "_row"} <= own
    assert not (own & TENSOR_PRIVATE)


@pytest.mark.parametrize(
    "path",
    sorted(p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py") if p != COMPAT),
)
def test_no_module_but_the_compat_module_touches_private_torch(path):
    uses = private_torch_uses((PACKAGE / path).read_text(encoding="utf-8"))
    assert not uses, (
        f"torch_polylap/{path} references private torch APIs {uses}: wrap them in "
        "torch_polylap/_torch_compat.py (with a comment saying why) and import from there."
    )


def test_the_compat_module_does_touch_them():
    """The scan sees the wrapped uses where they are (so a clean scan elsewhere means
    something)."""
    assert len(private_torch_uses(COMPAT.read_text(encoding="utf-8"))) >= 10
