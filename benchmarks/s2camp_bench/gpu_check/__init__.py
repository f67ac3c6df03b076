"""The GPU check: what one lent GPU answers, within one lease (docs/GPU-CHECK.md).

- ``config``: the check's options, its scene and the layout of its folder; ``environment``: what the machine has;
- ``processes``: the deadline and commands as subprocesses; ``records``: the JSON-lines records written as results
  are made;
- ``measured_train``: training runs in one process, measured as they go (``run_logs``: what they append);
- ``timing``, ``regime``, ``tests_stage``: the stages; ``report``: the report, rebuilt from the folder; ``cli``: the
  stages in order (``python -m s2camp_bench.gpu_check``);
- ``bundle``, ``wheels``, ``device_image``: the offline bundle of wheels (``python -m
  s2camp_bench.gpu_check.bundle``); ``lease.sh``: one lease as one call.
"""
