"""Summarise a mutmut run (``make mutation``) per module, with the surviving mutants judged equivalent.

Reads mutmut's results under ``mutants/`` and the list of equivalent mutants in ``docs/mutation-equivalents.toml``
(matched by module, function and the mutated source text, so the list survives mutmut renumbering its mutants).
Prints a markdown table per module (mutants, killed, survived, equivalent, no tests, timeout, mutants not run yet
by an interrupted run, kill rate over the non-equivalent mutants that ran), the equivalent survivors with their
reasons, and the diff of every survivor that is
neither killed nor listed as equivalent. ``--strict`` exits with status 1 while such survivors exist.

Run from the repository root after ``mutmut run`` (``make mutation`` does both); needs Python >= 3.11 (tomllib).
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import Counter
from dataclasses import dataclass
from difflib import unified_diff
from pathlib import Path

import libcst as cst
import tomllib
from mutmut.configuration import config
from mutmut.mutation.data import SourceFileMutationData
from mutmut.mutation.diff_apply import read_mutant_function, read_mutants_module, read_original_function
from mutmut.stats import status_by_exit_code

EQUIVALENTS = Path("docs/mutation-equivalents.toml")
NOT_KILLED = ("survived", "no tests", "timeout", "suspicious", "skipped")


@dataclass(frozen=True)
class Survivor:
    module: str
    function: str
    name: str
    status: str
    removed: str
    added: str
    diff: str


def _normalise(lines: list[str]) -> str:
    return " / ".join(re.sub(r"\s+", " ", line).strip() for line in lines if line.strip())


def _function_name(mutant_name: str) -> str:
    """``pkg.mod.xǁClassǁmethod__mutmut_3`` -> ``Class.method``; ``pkg.mod.x_func__mutmut_3`` -> ``func``."""
    mangled = mutant_name.rsplit(".", 1)[1].split("__mutmut_")[0]
    if mangled.startswith("xǁ"):
        return ".".join(part for part in mangled[2:].split("ǁ") if part)
    return mangled.removeprefix("x_")


_MODULES: dict[Path, object] = {}


def _diff(name: str, path: Path) -> str:
    """Unified diff of one mutant against the original function (mutmut's ``show``, parsing each file once)."""
    if path not in _MODULES:
        _MODULES[path] = read_mutants_module(path)
    module = _MODULES[path]
    original, mutant = (
        cst.Module([function]).code.strip()
        for function in (read_original_function(module, name), read_mutant_function(module, name))
    )
    return "\n".join(unified_diff(original.split("\n"), mutant.split("\n"), str(path), str(path), lineterm=""))


def _survivor(module: str, name: str, status: str, path: Path) -> Survivor:
    diff = _diff(name, path)
    body = [line for line in diff.splitlines()[2:] if not line.startswith("@@")]
    removed = _normalise([line[1:] for line in body if line.startswith("-")])
    added = _normalise([line[1:] for line in body if line.startswith("+")])
    return Survivor(module, _function_name(name), name, status, removed, added, diff)


def _matches(entry: dict, survivor: Survivor) -> bool:
    if entry["module"] != survivor.module or entry["function"] != survivor.function:
        return False
    if _normalise([entry["mutated"]]) != survivor.added:
        return False
    return "original" not in entry or _normalise([entry["original"]]) == survivor.removed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strict", action="store_true", help="exit 1 if a survivor is neither killed nor equivalent")
    args = parser.parse_args()

    equivalents = tomllib.loads(EQUIVALENTS.read_text())["equivalent"] if EQUIVALENTS.exists() else []
    used = [False] * len(equivalents)
    rows, equivalent_rows, unexplained = [], [], []
    totals: Counter = Counter()
    for path in sorted(Path(p) for p in config().only_mutate):
        data = SourceFileMutationData(path=path)
        data.load()
        if not data.exit_code_by_key:
            continue
        counts: Counter = Counter()
        for name, exit_code in sorted(data.exit_code_by_key.items()):
            status = "not run" if exit_code is None else status_by_exit_code[exit_code]
            counts["mutants"] += 1
            if status not in NOT_KILLED:
                counts["killed" if status == "killed" else status] += 1
                continue
            survivor = _survivor(str(path), name, status, path)
            hits = [i for i, entry in enumerate(equivalents) if _matches(entry, survivor)]
            if status == "survived" and hits:
                counts["equivalent"] += 1
                used[hits[0]] = True
                equivalent_rows.append((survivor, equivalents[hits[0]]["reason"]))
                continue
            counts[status.replace(" ", "_")] += 1
            unexplained.append(survivor)
        totals.update(counts)
        rows.append((str(path), counts))
    rows.append(("**all**", totals))

    print(
        "| module | mutants | killed | survived | equivalent | no tests | timeout | not run yet "
        "| kill rate (non-equivalent) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for module, c in rows:
        considered = c["mutants"] - c["equivalent"] - c["not run"]
        rate = f"{100.0 * c['killed'] / considered:.1f}%" if considered else "-"
        print(
            f"| {module} | {c['mutants']} | {c['killed']} | {c['survived']} | {c['equivalent']} | {c['no_tests']} "
            f"| {c['timeout']} | {c['not run']} | {rate} |"
        )
    print(f"\n## Equivalent survivors ({len(equivalent_rows)})\n")
    print("| module | function | mutation | why it cannot change behaviour |")
    print("|---|---|---|---|")
    for survivor, reason in equivalent_rows:
        change = f"`{survivor.removed}` -> `{survivor.added}`".replace("|", "\\|")
        print(f"| {Path(survivor.module).stem} | {survivor.function} | {change} | {reason} |")
    stale = [entry for entry, hit in zip(equivalents, used, strict=True) if not hit]
    if stale:
        print(f"\n## Listed as equivalent but not surviving any more ({len(stale)})\n")
        for entry in stale:
            print(f"- {entry['module']} {entry['function']}: `{entry['mutated']}`")
    if unexplained:
        print(f"\n## Not killed and not judged equivalent ({len(unexplained)})\n")
        for survivor in unexplained:
            print(f"### {survivor.name} ({survivor.status})\n```diff\n{survivor.diff}\n```")
    return 1 if args.strict and unexplained else 0


if __name__ == "__main__":
    sys.exit(main())
