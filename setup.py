"""Package layout only; all metadata is in pyproject.toml.

The benchmark scripts live in the top-level folder ``benchmarks/`` and install as the import package
``s2camp_ns.benchmarks`` (``package_dir`` mapping), so ``s2camp-bench`` works from any install; the declarative
``[tool.setuptools.packages.find]`` table cannot express that. Namespace discovery is used so that a subpackage
missing its ``__init__.py`` is still installed instead of silently dropped from regular (non-editable) installs.
"""

from setuptools import find_namespace_packages, setup

_SKIP = ["*__pycache__*"]
_benchmarks = ["s2camp_ns.benchmarks"] + [
    f"s2camp_ns.benchmarks.{name}" for name in find_namespace_packages("benchmarks", exclude=_SKIP)
]

setup(
    packages=find_namespace_packages(include=["s2camp_ns", "s2camp_ns.*"], exclude=_SKIP) + _benchmarks,
    package_dir={"s2camp_ns.benchmarks": "benchmarks"},
)
