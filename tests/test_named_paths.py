"""Every file or module the words name exists: paths (``s2camp_ns/core/camera.py``, ``tests/...``, ``docs/...``,
``benchmarks/...``) and dotted modules (``s2camp_ns.method.rays``, ``s2camp_bench.demo``) in the README, docs/ and
the code's comments, docstrings and strings.

Not read: the benchmarks' reports under docs/benchmarks/ (generated from the benchmark code, which is read, or kept as
the record of a settled experiment, with the commit that wrote them) and ``s2camp_ns/compat.py`` with its tests,
which name the module paths of earlier versions on purpose.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PATH = re.compile(r"(?<![\w./-])((?:s2camp_ns|benchmarks|tests|docs|tools|scripts)/[\w./-]*[\w/])")
"""A repository-relative path: a top-level folder, then anything up to a word character or a slash."""
MODULE = re.compile(r"(?<![\w./])((?:s2camp_ns|s2camp_bench)(?:\.[a-z_][a-z0-9_]*)+)")
"""A dotted name under one of our packages; its longest prefix that is a module must be a file."""
SKIPPED = ("docs/benchmarks/", "s2camp_ns/compat.py", "tests/test_compat.py", "tests/test_named_paths.py")
SOURCES = {"s2camp_ns": ROOT / "s2camp_ns", "s2camp_bench": ROOT / "benchmarks" / "s2camp_bench"}


def texts() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "Makefile", ROOT / "pyproject.toml", ROOT / "benchmarks" / "pyproject.toml"]
    files += sorted((ROOT / "docs").rglob("*.md"))
    for folder in ("s2camp_ns", "benchmarks", "tests", "tools", "scripts"):
        files += sorted(path for path in (ROOT / folder).rglob("*") if path.suffix in (".py", ".sh", ".md"))
    names = [path.relative_to(ROOT).as_posix() for path in files]
    return [path for path, name in zip(files, names, strict=True) if not name.startswith(SKIPPED)]


def path_exists(named: str, page: Path, pattern: bool) -> bool:
    """Whether ``named`` is a file or folder of the repository, or of the page's folder (a relative link in docs/);
    with ``pattern`` (the name goes on with ``{``, ``*``, ``<`` or ``-``), whether some file's path starts with it."""
    named = named.rstrip(".")
    for base in (ROOT, page.parent):
        if (base / named).exists() or (pattern and next(base.glob(named + "*"), None) is not None):
            return True
    return False


def module_exists(dotted: str) -> bool:
    """Whether ``dotted`` names a module of ours, or a name in one: its longest prefix that is a module or package
    (a file) must be at least a package of ours, and the first name after it must occur in that file (a name a
    module defines, or a package's submodule)."""
    parts = [part for part in dotted.split(".") if not part.startswith("__")]  # s2camp_ns.__version__
    source = SOURCES[parts[0]]
    for end in range(len(parts), 0, -1):
        folder = source.joinpath(*parts[1:end])
        file = folder.with_suffix(".py") if end > 1 and folder.with_suffix(".py").is_file() else folder / "__init__.py"
        if not file.is_file():
            continue
        if end == len(parts):
            return True
        following = parts[end]
        return (folder / following).is_dir() or re.search(rf"\b{following}\b", file.read_text("utf8")) is not None
    return False


def missing_names(path: Path) -> list[str]:
    text = path.read_text(encoding="utf8")
    missing = [
        match.group(1)
        for match in PATH.finditer(text)
        if not path_exists(match.group(1), path, text[match.end() : match.end() + 1] in "{*<-")
    ]
    missing += [dotted for dotted in MODULE.findall(text) if not module_exists(dotted)]
    return sorted(set(missing))


@pytest.mark.parametrize("path", texts(), ids=lambda path: path.relative_to(ROOT).as_posix())
def test_every_named_file_exists(path: Path) -> None:
    missing = missing_names(path)
    assert not missing, f"{path.relative_to(ROOT)} names what does not exist: {missing}"


def test_the_patterns_find_paths_and_modules(tmp_path: Path) -> None:
    """The check can fail: a named file that is not there and a module that is not there are both found."""
    page = tmp_path / "page.md"
    page.write_text("see `s2camp_ns/core/camera.py`, s2camp_ns/core/nowhere.py and s2camp_ns.data.nowhere.X\n")
    assert missing_names(page) == ["s2camp_ns.data.nowhere", "s2camp_ns/core/nowhere.py"]
    assert module_exists("s2camp_ns.core.camera.Intrinsics") and module_exists("s2camp_bench.demo")
