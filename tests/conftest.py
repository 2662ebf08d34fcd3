"""Shared fixtures: the Warp device under test, the shared assets folder and a preprocessing cache."""

import os
from pathlib import Path

import pytest

ASSETS = Path(__file__).resolve().parents[1].parent / "shared" / "assets"


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu", help="Warp device for the tests: cpu (default), cuda:0, or all")


def _devices(config):
    choice = config.getoption("--device")
    if choice != "all":
        return [choice]
    import warp as wp

    return ["cpu"] + [d.alias for d in wp.get_cuda_devices()]


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", _devices(metafunc.config))


@pytest.fixture
def asset():
    """Return a function giving the path of a shared asset, skipping the test when it is absent."""

    def get(name: str) -> Path:
        path = ASSETS / name
        if not path.exists():
            pytest.skip(f"shared asset {name} not found at {path} (../shared/assets is absent)")
        return path

    return get


@pytest.fixture(scope="session")
def prep_cache(tmp_path_factory) -> Path:
    """A preprocessing cache the session's simulation tests share: ``$WARPFEM_TEST_CACHE`` where set (a
    cache filled on a machine with Netgen lets these tests run on one without it, such as the GPU machine),
    else a fresh folder. Tests of the cache itself use folders of their own."""
    given = os.environ.get("WARPFEM_TEST_CACHE")
    return Path(given) if given else tmp_path_factory.mktemp("prep-cache")


@pytest.fixture(scope="session", autouse=True)
def default_cache(prep_cache):
    """The session's cache is also the default one (``$WARPFEM_CACHE``), so a test that prepares without
    naming a cache neither writes to the user's own nor misses what ``$WARPFEM_TEST_CACHE`` holds."""
    before = os.environ.get("WARPFEM_CACHE")
    os.environ["WARPFEM_CACHE"] = str(prep_cache)
    yield
    if before is None:
        del os.environ["WARPFEM_CACHE"]
    else:
        os.environ["WARPFEM_CACHE"] = before


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A test that has to prepare a body on a machine without Netgen (a GPU machine, whose cache lacks that
    body) is reported skipped, saying so, rather than failed."""
    outcome = yield
    report = outcome.get_result()
    error = call.excinfo
    if error is None or report.outcome != "failed" or "No module named 'netgen'" not in str(error.value):
        return
    try:
        import netgen  # noqa: F401
    except ImportError:
        report.outcome = "skipped"
        report.longrepr = (str(item.path), item.location[1] or 0, "needs Netgen to prepare a body the cache lacks")
