"""Shared fixtures: roads built in memory (no SUMO), the committed curved500 road and a fake SUMO
API; the property tests' draws seeded; the ``sumo`` marker enforced.

Helpers shared by several test files live in ``tests/fixtures_*.py`` (and ``bad_policies.py``,
``scripts.py``), never in a test file: no test file imports another (tests/test_markers.py).
"""

import functools
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

# every random draw from an explicit seed: hypothesis derives each test's examples from the
# test itself, so a run (CI's too) is repeatable; HYPOTHESIS_PROFILE=explore searches afresh
settings.register_profile("seeded", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "seeded"))

from fixtures_sumo import FakeSumoFactory

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads.road import Lane, Road
from safeil_sumo.sim import sumo_api

# ------------------------------------------------------------------------- the sumo marker
# A test that runs a SUMO simulation is marked ``sumo`` (``pytestmark = pytest.mark.sumo`` in a
# file where every test does, ``@pytest.mark.sumo`` on the test otherwise), so that
# ``python -m pytest -m "not sumo"`` is a subset that never starts SUMO. The mark is written on
# the test, where it moves with it, and checked here: every SUMO start in the test process
# goes through ``sumo_api.start``, which fails the running test when it is not marked. (A test
# whose SUMO runs in a subprocess or a spawned worker cannot be seen from here: mark it too.)
_running: list[pytest.Item] = []


def _start_only_when_marked(start):
    @functools.wraps(start)
    def guarded(*args, **kwargs):
        item = _running[-1] if _running else None
        if item is not None and item.get_closest_marker("sumo") is None:
            pytest.fail(f"{item.nodeid} starts SUMO but is not marked sumo: add "
                        "@pytest.mark.sumo (tests/conftest.py)", pytrace=False)
        return start(*args, **kwargs)

    return guarded


def pytest_configure(config: pytest.Config) -> None:
    sumo_api.start = _start_only_when_marked(sumo_api.start)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    _running.append(item)
    try:
        return (yield)
    finally:
        _running.pop()


def make_straight_road(length: float = 500.0, lanes: int = 3, width: float = 3.5) -> Road:
    """A straight road along +x; lane 0 is the rightmost, centred so lane 1 runs on y = 0."""
    out = []
    for i in range(lanes):
        y = (i - (lanes - 1) / 2) * width
        centre = Polyline(np.array([[0.0, y], [length, y]]))
        out.append(Lane(f"road_{i}", i, width, length, centre, centre.offset(width / 2),
                        centre.offset(-width / 2)))
    return Road(Path("straight_fixture.net.xml"), "road", tuple(out), lanes // 2, 20.0,
                length - 200.0, {})


@pytest.fixture
def straight_road() -> Road:
    return make_straight_road()


@pytest.fixture(scope="session")
def curved500():
    from safeil_sumo.roads.catalogue import resolve_net
    from safeil_sumo.roads.road import load_road

    return load_road(resolve_net("curved500"))


@pytest.fixture
def fake_sumo() -> FakeSumoFactory:
    """An ``api_factory`` for the loop (``run_scenario(..., api_factory=fake_sumo)``): each SUMO
    start makes a :class:`fixtures_sumo.FakeSumo`, kept in ``fake_sumo.made``."""
    return FakeSumoFactory()
