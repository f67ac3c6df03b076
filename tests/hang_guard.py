"""The suite's one hang guard: how long a test, or a process it waits for, may run before it is stopped.

A hang guard is no performance check. It exists only so that a run that hangs (a deadlocked process, a training
that never ends, a child that never answers) cannot block ``make test`` and CI forever; a slow machine must never
reach it. Performance claims belong to the benchmarks (``s2camp-bench``), not to test time limits.
"""

from __future__ import annotations

HANG_GUARD_S = 45 * 60
"""Seconds a test may run, fixtures included (``@pytest.mark.timeout(HANG_GUARD_S)``, pytest-timeout), and a process
it waits for may take (``subprocess.run(..., timeout=HANG_GUARD_S)``, ``Popen.wait``, ``Queue.get``). Where both
apply the test's limit ends it first, since it counts from the test's start.

Why 45 minutes: this is far above any run the suite guards, busy machine included. The slowest one is the quick
recovery benchmark (SfM and five ns-train variants). On a busy 2-core laptop it ran past the former 10-minute limit
while the whole suite took 56 minutes. Every other guarded run takes seconds to a few minutes. It is also
half of CI's 90-minute limit for the whole job: a single hung test is stopped, with pytest-timeout's stack dump
naming it, instead of running until CI kills the job without a report.

Timeouts that belong to the behaviour under test are not hang guards and keep their own values: a waiter that must
give up, a lock wait, the grace period between SIGINT and SIGKILL.
"""
