"""A griffe extension that turns the Sphinx roles of the docstrings into API-reference links.

The package's docstrings cross-reference each other with Sphinx roles (``:func:`laplacian```,
``:class:`~torch_polylap.sparse.SparseOperator```), which Markdown would show verbatim. This
extension, loaded by mkdocstrings (``mkdocs.yml``), rewrites every role before the docstrings
are rendered:

- the target is resolved in the scope of the object whose docstring it is (module members and
  imports, relative module paths such as ``:mod:`.obj```);
- if the object it names is rendered in the API reference, the role becomes an autorefs link to
  the *public* path under which it is rendered (``torch_polylap.laplacian``, not the internal
  module that defines it), so the reference keeps working while internal modules move;
- anything else (private helpers, internal modules, other libraries) becomes inline code.

The public paths are the exports (``__all__``) of the modules listed in ``documented``, in
that order: an object exported by several of them is linked to the first. The reference pages
must render every export of those modules (mkdocs' strict build fails on a dangling link).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(
    r":(?:py:)?(?P<role>func|class|meth|mod|data|attr|obj|exc|const|ref|doc):"
    r"`(?P<body>[^`]+)`"
)
_TITLED = re.compile(r"^(?P<title>.*?)\s*<(?P<target>[^<>]+)>$")


class SphinxRoles(griffe.Extension):
    """Rewrite Sphinx roles in every docstring of the loaded package (see the module doc)."""

    def __init__(self, documented: list[str] | None = None) -> None:
        super().__init__()
        self.documented = list(documented or [])
        self.public: dict[str, str] = {}

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        self.public = {}
        for path in self.documented:
            module = _lookup(pkg, path)
            if module is None:
                continue
            if module is not pkg:  # a subpackage page renders the module itself too
                self.public.setdefault(module.path, path)
            for name in _exports(module):
                member = _shadowing_object(module, name)
                canonical = _canonical(member) if member is not None else None
                if canonical is not None and _rendered(member):
                    self.public.setdefault(canonical, f"{path}.{name}")
        for obj in _walk(pkg):
            if obj.docstring is not None and ":" in obj.docstring.value:
                obj.docstring.value = _ROLE.sub(
                    lambda m, obj=obj: self._replace(pkg, obj, m), obj.docstring.value
                )

    def _replace(self, pkg: griffe.Module, obj: griffe.Object, match: re.Match) -> str:
        body = match.group("body").strip()
        titled = _TITLED.match(body)
        title, target = (titled["title"], titled["target"]) if titled else (None, body)
        short = target.startswith("~")
        target = target.lstrip("~").rstrip("()")
        if title is None:
            title = target.rsplit(".", 1)[-1] if short else target.lstrip(".")
        link = self._public_path(pkg, obj, target)
        return f"[`{title}`][{link}]" if link else f"`{title}`"

    def _public_path(self, pkg: griffe.Module, obj: griffe.Object, target: str) -> str | None:
        """The rendered path of ``target`` as seen from ``obj``, or ``None``."""
        resolved = _resolve(pkg, obj, target)
        if resolved is None:
            return None
        canonical = _canonical(resolved)
        if canonical is None:
            return None
        if canonical in self.public:
            return self.public[canonical]
        # A member (method, attribute) of a rendered class: link to the class.
        parts = canonical.split(".")
        for cut in range(len(parts) - 1, 0, -1):
            owner = ".".join(parts[:cut])
            if owner in self.public:
                return self.public[owner]
        return None


def _walk(obj: griffe.Object):
    """Every object of the package, aliases excluded (their docstrings are their targets')."""
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)


def _exports(module: griffe.Module) -> list[str]:
    """The module's ``__all__``; when griffe cannot evaluate it (the top level derives it at
    import time), every member without a leading underscore that is not a submodule."""
    if module.exports:
        return list(module.exports)
    return [
        name
        for name, member in module.members.items()
        if not name.startswith("_") and not _is_submodule(module, member)
    ]


def _shadowing_object(module: griffe.Module, name: str) -> griffe.Object | griffe.Alias | None:
    """The member ``name`` of ``module`` as Python sees it.

    ``from .planarize import planarize`` in a package binds the function over the submodule of
    the same name; griffe keeps the submodule. The function is then the export (the reference
    page renders it explicitly, under an anchor with the public path).
    """
    member = module.members.get(name)
    if member is not None and _is_submodule(module, member) and name in member.members:
        return member.members[name]
    return member


def _is_submodule(module: griffe.Module, member: griffe.Object | griffe.Alias) -> bool:
    try:
        return member.is_module and member.parent is module
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return False


def _rendered(member: griffe.Object | griffe.Alias) -> bool:
    """Whether mkdocstrings renders the object (it skips objects without any docstring)."""
    try:
        target = member.final_target if member.is_alias else member
        return not target.is_module and target.has_docstrings
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return False


def _lookup(pkg: griffe.Module, path: str) -> griffe.Object | None:
    if path == pkg.path:
        return pkg
    if not path.startswith(pkg.path + "."):
        return None
    try:
        return pkg[path[len(pkg.path) + 1 :]]
    except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _canonical(obj: griffe.Object | griffe.Alias) -> str | None:
    try:
        return obj.final_target.path if obj.is_alias else obj.path
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _resolve(pkg: griffe.Module, obj: griffe.Object, target: str) -> griffe.Object | None:
    """The object ``target`` names in the scope of ``obj`` (dotted, absolute or relative)."""
    if target.startswith("."):  # relative to the docstring's package
        module = obj.module
        base = module if module.is_package else module.parent
        return _lookup(pkg, f"{base.path}.{target.lstrip('.')}")
    if target.startswith(pkg.path + ".") or target == pkg.path:
        return _lookup(pkg, target)
    head, _, rest = target.partition(".")
    scope: griffe.Object | None = obj
    while scope is not None:
        try:
            path = scope.resolve(head)
        except griffe.NameResolutionError:
            scope = scope.parent
            continue
        found = _lookup(pkg, path)
        if found is None:
            return None
        if rest:
            found = _lookup(pkg, f"{_canonical(found) or found.path}.{rest}")
        return found
    return None
