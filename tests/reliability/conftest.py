"""Reliability suite: a hang net on every test and a summary of how many inputs were tried."""

import pytest
from reliability import fuzzkit

#: Seconds a reliability test may run in CI mode before pytest-timeout calls it a hang.
CI_TIMEOUT = 240


def pytest_collection_modifyitems(config, items):
    scale = max(1.0, fuzzkit.examples(30) / 30)
    for item in items:
        if "reliability" in item.nodeid.split("/") and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(int(CI_TIMEOUT * scale)))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if not fuzzkit.TRIED:
        return
    mode = (
        f"long mode, {fuzzkit.EXAMPLES_ENV}={fuzzkit.examples(0)}"
        if fuzzkit.long_mode()
        else "CI mode"
    )
    terminalreporter.write_sep("-", f"reliability inputs tried ({mode})")
    for area in sorted(fuzzkit.TRIED):
        tried, rejected, untyped = (
            fuzzkit.TRIED[area],
            fuzzkit.REJECTED[area],
            fuzzkit.UNTYPED[area],
        )
        terminalreporter.write_line(
            f"{area:<22} {tried:>7} inputs: {rejected:>7} typed errors, {tried - rejected - untyped:>7} clean results, "
            f"{untyped} untyped exceptions"
        )
    terminalreporter.write_line(f"{'total':<22} {sum(fuzzkit.TRIED.values()):>7} inputs")
    if fuzzkit.OUTCOMES:
        terminalreporter.write_sep("-", "numerical edge cases: outcome per method")
        for (method, scenario), outcome in sorted(fuzzkit.OUTCOMES.items()):
            terminalreporter.write_line(f"{method:<20} {scenario:<22} {outcome}")
