"""Where the test suite's time goes: tracing, lowering and XLA compiling per test, from JAX's own compile events.

    PYTHONPATH=benchmarks SUITE_COMPILE_TIME=FILE python -m pytest -q -n auto -p suite_compile_time [TESTS]
    python benchmarks/suite_compile_time.py FILE [--top 40]

As a pytest plugin (the first line; every xdist worker loads it) it appends
one JSON line per test to FILE: the test's wall seconds (setup, call and
teardown) and the seconds and counts of `jax.monitoring`'s duration events
recorded while it ran, among them `/jax/core/compile/jaxpr_trace_duration`
(tracing), `.../jaxpr_to_mlir_module_duration` (lowering) and
`.../backend_compile_duration` (XLA compiling; not recorded for a program
read back from the persistent cache, whose reads are
`/jax/compilation_cache/cache_retrieval_time_sec`). Start FILE empty: lines
are appended. Run as a script (the second line) it sums FILE: the totals,
then per test file and per test function, heaviest first. Figures are in
benchmarks/README.md, "The test suite on CI".
"""

import argparse
import collections
import json
import os
import time
from pathlib import Path

import pytest

TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
COMPILE = "/jax/core/compile/backend_compile_duration"
CACHE_READ = "/jax/compilation_cache/cache_retrieval_time_sec"

_events: collections.Counter = collections.Counter()


def _record(event: str, duration: float, **_) -> None:
    _events[event] += duration
    _events[event + "#count"] += 1


def pytest_configure(config) -> None:
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_record)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Times the whole protocol of one test (setup, call, teardown) and writes its row."""
    _events.clear()
    started = time.perf_counter()
    yield
    row = {"test": item.nodeid, "wall": time.perf_counter() - started, **_events}
    with open(os.environ["SUITE_COMPILE_TIME"], "a") as out:
        out.write(json.dumps(row) + "\n")



def _table(title: str, groups: dict[str, collections.Counter], top: int) -> None:
    print(f"\n| {title} | tests | wall s | compiling s | programs compiled | lowering s | tracing s |")
    print("|---|---|---|---|---|---|---|")
    for name, sums in sorted(groups.items(), key=lambda item: -item[1]["wall"])[:top]:
        print(f"| {name} | {sums['tests']} | {sums['wall']:.1f} | {sums[COMPILE]:.1f} | {sums[COMPILE + '#count']:.0f} "
              f"| {sums[LOWER]:.1f} | {sums[TRACE]:.1f} |")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("file", type=Path, help="the JSON lines the plugin wrote")
    parser.add_argument("--top", type=int, default=40, help="rows per table (default: %(default)s)")
    args = parser.parse_args()
    rows = [json.loads(line) for line in args.file.read_text().splitlines() if line.strip()]
    total, by_file, by_function = collections.Counter(), {}, {}
    for row in rows:
        path, _, rest = row.pop("test").partition("::")
        row["tests"] = 1
        for groups, key in ((by_file, path), (by_function, f"{path}::{rest.split('[')[0]}")):
            groups.setdefault(key, collections.Counter()).update(row)
        total.update(row)
    print(f"{total['tests']} tests, {total['wall']:.1f} s of tests; compiling {total[COMPILE]:.1f} s "
          f"({total[COMPILE + '#count']:.0f} programs), lowering {total[LOWER]:.1f} s, tracing {total[TRACE]:.1f} s, "
          f"cache reads {total[CACHE_READ]:.1f} s ({total[CACHE_READ + '#count']:.0f})")  # fmt: skip
    _table("file", by_file, args.top)
    _table("test function", by_function, args.top)


if __name__ == "__main__":
    main()
