"""How the suite runs across the cores (``scripts/test.sh``: ``pytest -n auto --dist loadgroup``).

Tests marked ``xdist_group`` run on one worker: the files whose module-scoped fixtures are
expensive (built once, not once per worker that got one of their tests) and the tests that
start a local Ray instance. pytest-xdist names a test's group by appending ``@group`` to its
node id (``item._nodeid``); pytest 9.2 keeps the node id in a structured field instead, so that
append is lost and every group is silently ignored (pytest-dev/pytest-xdist#1386). The hook
below carries the appended id over; it does nothing where xdist's own change takes effect.
"""

import pytest


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    if not getattr(config.option, "loadgroup", False):
        return
    for item in items:
        appended = item.__dict__.get("_nodeid")
        if isinstance(appended, str) and appended != item.nodeid and hasattr(item, "_id"):
            from _pytest.nodeid import NodeId

            item._id = NodeId.parse(appended)
