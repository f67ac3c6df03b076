"""Benchmarks that reproduce the paper's claims next to their baselines (installed as ``s2camp_bench``).

Run them with ``s2camp-bench <name>``; each writes a markdown table and PNG plots under ``outputs/benchmarks/``, or
wherever ``--output-dir`` says (``--output-dir docs/benchmarks`` rewrites the committed ones).
"""
