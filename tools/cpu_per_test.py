"""Where the test suite's processor time goes: each test's CPU seconds, and their sum.

A pytest plugin and a report. Wall time (pytest's ``--durations``) on a shared two-core
machine mostly measures what else ran at the time; CPU seconds are what a test costs
wherever it runs, and they add up to what the suite costs beside other work. Run::

    PYTHONPATH=tools python -m pytest -p cpu_per_test --cpu-out /tmp/cpu-a
    python tools/cpu_per_test.py /tmp/cpu-a            # the 25 costliest tests, and the total
    python tools/cpu_per_test.py /tmp/cpu-a /tmp/cpu-b  # two runs side by side, test by test

Each test's time is its process's own CPU (user + system) over the test's setup, call and
teardown, and that of the child processes it waited for (a ``magrun`` command, a compiler,
a run's worker pool). Not counted: what the test started and did not wait for (a Ray
cluster's daemons and workers, a viewer left to the session), and the collection and
start of pytest's own workers. A library compiled into the cache is charged to the first
test that needs it, so compare whole runs with the same cache state (``XDG_CACHE_HOME`` of
its own for a fresh one). Written by hand: pytest and pytest-xdist report wall time only.
"""

from __future__ import annotations

import json
import os
import resource
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--cpu-out", metavar="DIR", default=None,
        help="folder for each test's CPU seconds (tools/cpu_per_test.py), one file per process",
    )  # fmt: skip


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    out = item.config.getoption("--cpu-out")
    own, children = _cpu(resource.RUSAGE_SELF), _cpu(resource.RUSAGE_CHILDREN)
    yield
    if out is None:
        return
    record = {
        "test": item.nodeid,
        "self_s": _cpu(resource.RUSAGE_SELF) - own,
        "children_s": _cpu(resource.RUSAGE_CHILDREN) - children,
    }
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f"{os.getpid()}.jsonl", "a", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")


def read(folder: Path) -> dict[str, float]:
    """Each test's CPU seconds (own + children) in a run's folder."""
    seconds: dict[str, float] = {}
    for path in sorted(folder.glob("*.jsonl")):
        for line in path.read_text(encoding="utf-8").splitlines():
            record: dict[str, Any] = json.loads(line)
            seconds[record["test"]] = record["self_s"] + record["children_s"]
    return seconds


def main(argv: list[str]) -> int:
    if not 1 <= len(argv) <= 2 or not all(Path(a).is_dir() for a in argv):
        print("usage: python tools/cpu_per_test.py RUN_DIR [OTHER_RUN_DIR]", file=sys.stderr)
        return 2
    runs = [read(Path(a)) for a in argv]
    for folder, run in zip(argv, runs, strict=True):
        print(f"{folder}: {len(run)} tests, {sum(run.values()):.0f} CPU s")
    if len(runs) == 1:
        for test, s in sorted(runs[0].items(), key=lambda kv: -kv[1])[:25]:
            print(f"{s:7.1f}  {test}")
        return 0
    a, b = runs
    both = sorted(set(a) & set(b), key=lambda t: b[t] - a[t])
    print("CPU s: first run, second run, change")
    for test in both if len(both) <= 24 else both[:12] + both[-12:]:
        print(f"{a[test]:7.1f} {b[test]:7.1f} {b[test] - a[test]:+7.1f}  {test}")
    for label, run, other in (("first", a, b), ("second", b, a)):
        only = set(run) - set(other)
        if only:
            print(f"only in the {label}: {len(only)} tests, {sum(run[t] for t in only):.0f} CPU s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
