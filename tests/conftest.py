import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def _shared_cache(tmp_path_factory):
    """Solved optima (Pareto fronts) are cached once per test session, never in the user's home."""
    if "WL_CACHE_DIR" not in os.environ:
        os.environ["WL_CACHE_DIR"] = str(tmp_path_factory.mktemp("wl_cache"))
    yield
