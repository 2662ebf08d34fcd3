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
