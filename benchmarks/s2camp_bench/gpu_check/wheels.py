"""Wheels for the lent GPU machine (Python 3.12, x86_64 Linux): fetched from the package registry, built from an
sdist where the registry has no such wheel, this repository's own packages, and wheels slimmed of files nothing
there reads."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
             "manylinux1_x86_64")  # fmt: skip
"""The wheel platforms pip may pick (the machine's glibc is newer than 2.28)."""


def run_quietly(command: list[str]) -> str | None:
    """Run ``command``; None when it succeeded, else the end of its output."""
    try:
        result = subprocess.run(command, capture_output=True, text=True)
    except OSError as error:
        return str(error)
    output = (result.stdout + result.stderr).strip()
    return None if result.returncode == 0 else (output.splitlines()[-1] if output else f"status {result.returncode}")


def fetch(packages: dict[str, str], folder: Path, python312: str) -> list[str]:
    """Download each package's Python 3.12 wheel into ``folder`` (``pip download``, no dependencies), or build it from
    its sdist with the interpreter ``python312`` where the registry has none; what could not be had, and why."""
    platforms = [option for platform in PLATFORMS for option in ("--platform", platform)]
    download = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                "--python-version", "3.12", "--implementation", "cp", *platforms, "--dest", str(folder)]  # fmt: skip
    missing = []
    for name, version in packages.items():
        requirement = f"{name}=={version}"
        if run_quietly([*download, requirement]) is None:
            print(f"  fetched {requirement}", flush=True)
            continue
        is_312 = [python312, "-c", "import sys; assert sys.version_info[:2] == (3, 12), sys.version"]
        problem = run_quietly(is_312) or run_quietly(
            [python312, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-binary", ":all:", "--wheel-dir",
             str(folder), requirement]
        )  # fmt: skip
        if problem is None:
            print(f"  built {requirement} from its sdist with {python312}", flush=True)
        else:
            missing.append(f"{requirement}: no Python 3.12 wheel on the registry, and no build with {python312!r} "
                           f"(a Python 3.12: --python312): {problem}")  # fmt: skip
    return missing


def own_wheel(repository: Path, project: str, folder: Path) -> Path:
    """A wheel of the project in ``repository``'s folder ``project`` ("." for the repository root), built from the
    files git tracks or would track (no build outputs, no local links) copied aside, so that the working tree gets
    no build folders; written into ``folder``."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard", "--", project],
        cwd=repository, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="s2camp-wheel-") as temporary:
        source = Path(temporary) / "source"
        for name in filter(None, listed):
            path = repository / name
            if path.is_file() and not path.is_symlink():
                (source / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(path, source / name)
        before = set(folder.glob("*.whl"))
        subprocess.run(
            [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "--wheel-dir",
             str(folder), str(source / project)],
            check=True, capture_output=True,
        )  # fmt: skip
    (built,) = set(folder.glob("*.whl")) - before
    return built


def slim_wheel(path: Path, drop: tuple[str, ...]) -> int:
    """Rewrite the wheel ``path`` without its members under the folders ``drop`` (their lines left out of RECORD
    too); the bytes saved."""
    size = path.stat().st_size
    temporary = path.with_suffix(".slim")
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(temporary, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as out:
        for member in source.infolist():
            if member.filename.startswith(drop):
                continue
            data = source.read(member)
            if member.filename.endswith(".dist-info/RECORD"):
                lines = data.decode().splitlines(keepends=True)
                data = "".join(line for line in lines if not line.startswith(drop)).encode()
            out.writestr(member, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
    temporary.replace(path)
    return size - path.stat().st_size
