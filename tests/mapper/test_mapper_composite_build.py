"""The first use of the C++ compositing extension says in one line that it is building (issue 18:
the first run compiled for 21 s in silence); a cached build says nothing."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch.utils.cpp_extension as cpp_extension

from mogs_node.mapper import composite


@pytest.fixture
def fresh_extension(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No extension loaded yet, a build root in ``tmp_path`` and a ``load`` that builds nothing."""
    monkeypatch.setattr(composite, "_EXT", None)
    monkeypatch.setattr(composite, "_EXT_FAILED", False)
    monkeypatch.delenv("MOGS_NO_CPP_EXT", raising=False)
    monkeypatch.delenv("TORCH_EXTENSIONS_DIR", raising=False)
    monkeypatch.setattr(cpp_extension, "get_default_build_root", lambda: str(tmp_path))
    monkeypatch.setattr(cpp_extension, "load", lambda **kw: "loaded:" + kw["name"])
    return tmp_path


def _build_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if "building the C++" in r.getMessage()]


def test_first_build_prints_one_line(fresh_extension: Path, caplog) -> None:
    with caplog.at_level(logging.INFO, logger=composite.log.name):
        assert composite.load_cpp_extension() == "loaded:" + composite.extension_name()
        assert (
            composite.load_cpp_extension() == "loaded:" + composite.extension_name()
        )  # cached in-process
    (line,) = _build_lines(caplog)
    assert str(fresh_extension) in line


def test_a_cached_build_prints_nothing(fresh_extension: Path, caplog) -> None:
    import torch

    d = fresh_extension / f"mogs_torch{torch.__version__}" / composite.extension_name()
    d.mkdir(parents=True)
    (d / f"{composite.extension_name()}.so").write_bytes(b"")
    with caplog.at_level(logging.INFO, logger=composite.log.name):
        assert composite.load_cpp_extension() == "loaded:" + composite.extension_name()
    assert _build_lines(caplog) == []


def test_the_build_compiles_a_copy_inside_its_own_directory(
    fresh_extension: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """torch's build file names the source path: two checkouts of one source at different paths
    (worktrees) must compile the same file, or each rebuilds the shared module over the other."""
    seen: dict = {}
    monkeypatch.setattr(cpp_extension, "load", lambda **kw: seen.update(kw) or "loaded")
    other = fresh_extension / "other_root"
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(other))  # torch's own override is honoured
    assert composite.load_cpp_extension() == "loaded"
    (src,) = seen["sources"]
    assert Path(src).parent == Path(seen["build_directory"])
    assert Path(seen["build_directory"]).is_relative_to(other)
    assert Path(src).read_bytes() == composite._SOURCE.read_bytes()
