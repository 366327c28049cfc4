"""A command whose optional dependency is missing says which extra installs it (exit 2)."""

from __future__ import annotations

import builtins

import pytest

from torch_polylap.cli import main


@pytest.mark.parametrize("module,extra", [("mpl_toolkits", "plot"), ("matplotlib", "plot")])
def test_missing_plotting_extra_is_named(monkeypatch, tmp_path, capsys, module, extra):
    real_import = builtins.__import__

    def without(name, *args, **kwargs):
        if name.split(".")[0] == module:
            raise ModuleNotFoundError(f"No module named {module!r}", name=module)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", without)
    status = main(["demo", "-o", str(tmp_path)])
    err = capsys.readouterr().err
    assert status == 2, err
    # one line of its own after the progress bar's
    assert err.endswith(f"pip install 'torch_polylap[{extra}]'\n"), err
    assert "internal error" not in err and err.count("polylap: error") == 1
