"""ns-train's own parse of benchmark command lines, in a subprocess registered as the benchmarks' runs are.

``s2camp-bench-data`` is no installed entry point (a user's ``ns-train`` never imports the benchmarks): nerfstudio
builds its data parser choices once, at import, so a command that names it parses only in a process started with
``ns_train_environment()``, as ``s2camp-bench`` starts its ``ns-train`` runs.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

from s2camp_bench.data_parser import ns_train_environment

_SCRIPT = """
import pickle, sys
import tyro
from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion
commands = pickle.load(sys.stdin.buffer)
with open(sys.argv[1], "wb") as output:  # not stdout: nerfstudio prints there
    pickle.dump([tyro.cli(AnnotatedBaseConfigUnion, args=args) for args in commands], output)
"""


def parse_ns_train(commands: list[list[str]]) -> list:
    """The ``TrainerConfig`` of each ``ns-train`` command line (the executable first, as the benchmarks build them)."""
    with tempfile.TemporaryDirectory() as folder:
        return _parse(commands, Path(folder) / "configs.pickle")


def _parse(commands: list[list[str]], output: Path) -> list:
    result = subprocess.run(
        [sys.executable, "-c", _SCRIPT, str(output)],
        input=pickle.dumps([command[1:] for command in commands]),
        capture_output=True,
        env=ns_train_environment(),
        timeout=300,
    )
    assert result.returncode == 0, result.stderr.decode(errors="replace")[-3000:]
    return pickle.loads(output.read_bytes())
