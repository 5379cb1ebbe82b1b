import os
import shutil
import tempfile

import pytest


def pytest_configure(config):
    """One folder of compiled NLP functions (mpc.controller.codegen) for the whole run, made before the
    test processes start: they share its libraries (the first to need one builds it) instead of compiling
    each its own."""
    if not hasattr(config, "workerinput") and "WL_CODEGEN_DIR" not in os.environ:
        config._wl_codegen_dir = os.environ["WL_CODEGEN_DIR"] = tempfile.mkdtemp(prefix="wl_codegen_")


def pytest_unconfigure(config):
    if getattr(config, "_wl_codegen_dir", None):
        shutil.rmtree(config._wl_codegen_dir, ignore_errors=True)


@pytest.fixture(scope="session", autouse=True)
def _shared_cache(tmp_path_factory):
    """Solved optima (Pareto fronts) are cached once per test session, never in the user's home."""
    if "WL_CACHE_DIR" not in os.environ:
        os.environ["WL_CACHE_DIR"] = str(tmp_path_factory.mktemp("wl_cache"))
    yield
