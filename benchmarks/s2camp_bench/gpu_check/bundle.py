"""``python -m s2camp_bench.gpu_check.bundle``: the wheels a lent GPU machine (no registry, its own Python 3.12 and
torch: ``DEVICE_IMAGE``) needs to run the check offline: the packages the training path imports (``TRAINING_MODULES``,
in a fresh process) that it lacks, at this checkout's versions (``wheels``), slimmed (``SLIM``), and a wheel of each
of this repository's packages (``OWN_PROJECTS``). Written to ``--output`` (``.whl/``, ignored by git) only within
``--limit-mib`` with the files git tracks (what one call carries); ``--dry-run`` lists it and fetches nothing.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from .wheels import fetch, own_wheel, slim_wheel

DEVICE_IMAGE = Path(__file__).with_name("device_image.txt")
"""The packages the lent machines' image holds, one a line (``#``: a comment)."""

TRAINING_MODULES = (
    "nerfstudio.scripts.train", "nerfstudio.configs.method_configs", "nerfstudio.engine.trainer",
    "nerfstudio.models.splatfacto", "nerfstudio.data.datamanagers.full_images_datamanager", "torch.utils.tensorboard",
    "torchmetrics.image.lpip", "gsplat.rendering", "pycolmap", "pytest", "s2camp_ns.method_config",
    "s2camp_bench.evaluation", "s2camp_bench.gpu_check.cli", "s2camp_bench.gpu_check.measured_train",
)  # fmt: skip
"""What the check and its ``cuda`` tests import on the machine."""
OWN_PROJECTS = {"s2camp-ns": ".", "s2camp-bench": "benchmarks"}
"""This repository's distributions and the folders of their project files: built here, never fetched."""
SLIM = {
    "gsplat": ("gsplat/cuda/csrc/third_party/glm/doc/", "gsplat/cuda/csrc/third_party/glm/test/"),
    "tensorly": ("tensorly/datasets/data/",), "viser": ("viser/client/src/", "viser/client/public/"),
    "torch-fidelity": ("tests/",),
}  # fmt: skip
"""Folders left out of a wheel: glm's manual and tests (gsplat compiles with glm's headers only), tensorly's sample
data sets, viser's client sources (it serves its built client), torch-fidelity's tests (a top-level ``tests``)."""
LISTING = """
import importlib, importlib.metadata as metadata, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
owners = metadata.packages_distributions()
found = {d for module in list(sys.modules) for d in owners.get(module.split(".")[0], [])}
print(json.dumps({d: metadata.version(d) for d in sorted(found)}))
"""


def normalized(name: str) -> str:
    """A distribution name as the registry compares them (PEP 503)."""
    return re.sub(r"[-_.]+", "-", name).lower()


@dataclass
class BundleConfig:
    """Prepare the offline bundle of wheels for a lent GPU machine."""

    output: Path = Path(".whl")
    """The bundle's folder (ignored by git); replaced only by a bundle within the limit."""
    limit_mib: float = 64.0
    """The most that one call to the machine carries: the bundle plus the files git tracks."""
    python312: str = "python3.12"
    """A Python 3.12 interpreter to build wheels from sdists with (with pyenv: ``PYENV_VERSION=3.12.1``)."""
    dry_run: bool = False
    """List the packages and what would be done with each; fetch and build nothing."""


def to_carry(distributions: dict[str, str]) -> dict[str, str]:
    """Of ``distributions`` (name -> version), those the machine lacks, this repository's own left out."""
    listed = [line.strip() for line in DEVICE_IMAGE.read_text().splitlines() if not line.startswith("#")]
    present = {normalized(name) for name in (*filter(None, listed), *OWN_PROJECTS)}
    return {name: version for name, version in distributions.items() if normalized(name) not in present}


def training_packages() -> dict[str, str]:
    """Name -> version of what ``TRAINING_MODULES`` import (read in a fresh process) that the machine lacks."""
    result = subprocess.run([sys.executable, "-c", LISTING, *TRAINING_MODULES], capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"importing the training path failed:\n{result.stderr[-3000:]}")
    return to_carry(json.loads(result.stdout.strip().splitlines()[-1]))


def mib(size: int) -> str:
    return f"{size / 2**20:.1f} MiB"


def build(config: BundleConfig, repository: Path, packages: dict[str, str]) -> int:
    """Fetch, build and slim the wheels into a staging folder, then into ``config.output`` if within the limit;
    the exit status."""
    staging = config.output.with_name(config.output.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    missing = fetch(packages, staging, config.python312)
    for folder in OWN_PROJECTS.values():
        own_wheel(repository, folder, staging)
    for wheel in staging.glob("*.whl"):
        if normalized(wheel.name.split("-")[0]) in SLIM:
            print(f"  slimmed {wheel.name} by {mib(slim_wheel(wheel, SLIM[normalized(wheel.name.split('-')[0])]))}")
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=repository, capture_output=True, check=True).stdout
    tracked = (repository / name for name in listed.decode().split("\0") if name)
    tree = sum(path.stat().st_size for path in tracked if path.is_file() and not path.is_symlink())
    bundle = sum(wheel.stat().st_size for wheel in staging.glob("*.whl"))
    print(f"bundle: {len(list(staging.glob('*.whl')))} wheels, {mib(bundle)}; tracked files: {mib(tree)}; "
          f"together {mib(bundle + tree)} of {config.limit_mib:g} MiB", flush=True)  # fmt: skip
    if missing:
        print("missing (the check cannot run without them):\n  " + "\n  ".join(missing), flush=True)
        return 1
    if bundle + tree > config.limit_mib * 2**20:
        print(f"refused: over the limit of {config.limit_mib:g} MiB; {config.output} left as it was", flush=True)
        return 1
    shutil.rmtree(config.output, ignore_errors=True)
    staging.rename(config.output)
    print(f"bundle ready in {config.output}", flush=True)
    return 0


def main(config: BundleConfig) -> int:
    repository = Path(__file__).resolve().parents[3]
    if not all((repository / folder / "pyproject.toml").is_file() for folder in OWN_PROJECTS.values()):
        raise SystemExit(f"the bundle is made from a checkout of this repository (editable installs), not {repository}")
    packages = training_packages()
    print(f"the training path imports {len(packages)} packages the machine lacks:", flush=True)
    for name, version in packages.items():
        slim = f" (slimmed: without {', '.join(SLIM[normalized(name)])})" if normalized(name) in SLIM else ""
        print(f"  {name}=={version}{slim}")
    for name, folder in OWN_PROJECTS.items():
        print(f"  {name} (this checkout's {folder}, built as a wheel)")
    return 0 if config.dry_run else build(config, repository, packages)


if __name__ == "__main__":
    raise SystemExit(main(tyro.cli(BundleConfig, description=__doc__)))
