"""Shared fixtures: the real-data folder beside the checkout, and float64 JAX."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """A path under ``../shared/data``; skips the calling test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not found at {path} (needs ../shared/data beside the checkout)")
    return path


@pytest.fixture
def euroc_micro() -> Path:
    """Root of the real EuRoC V1_01 micro sequence (the folder holding ``mav0``)."""
    return shared_path("euroc_v101_micro")


@pytest.fixture
def x64():
    """Run the test body with 64-bit JAX types enabled."""
    with jax.enable_x64(True):
        yield


@pytest.fixture(scope="session", autouse=True)
def _no_cli_cache_in_home():
    """The commands' persistent compile cache (``uavcal_jax.xla_cache``) stays off in tests:
    nothing is written under the user's home, and no test module inherits a cache another
    module's CLI call switched on."""
    before = os.environ.get("UAVCAL_JAX_CACHE")
    os.environ["UAVCAL_JAX_CACHE"] = "off"
    yield
    if before is None:
        os.environ.pop("UAVCAL_JAX_CACHE", None)
    else:
        os.environ["UAVCAL_JAX_CACHE"] = before


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """Drop every compiled executable after each test module. A single process runs the
    whole suite, and XLA:CPU keeps each executable's JIT code mapped: two full runs that kept
    them all segfaulted inside XLA (once compiling, once serialising) late in the suite, where
    the same modules alone pass. Modules do not share compiled functions, so nothing is
    recompiled that would not be anyway."""
    yield
    jax.clear_caches()


@pytest.fixture(scope="module")
def xla_cache(tmp_path_factory):
    """A persistent XLA compilation cache for the test module that asks for it, in one
    session-wide folder, so identical computations compiled by several tests or modules
    (detector training steps, say) compile once. It is switched off again after the module:
    the cache is process-wide, and writing every later module's executables to it is slow and
    has crashed XLA:CPU's executable serialisation (a segfault in ``serialize`` seen once in a
    full run)."""
    from jax.experimental.compilation_cache import compilation_cache as cc

    if jax.config.jax_compilation_cache_dir:  # the caller chose a cache: leave it alone
        yield
        return
    jax.config.update("jax_compilation_cache_dir",
                      str(tmp_path_factory.getbasetemp() / "xla_cache"))
    cc.reset_cache()
    yield
    jax.config.update("jax_compilation_cache_dir", None)
    cc.reset_cache()


#: Seconds the heaviest modules take on CI (2 cores, two workers, ``heavy`` tests left out;
#: measured with ``PYTEST_ADDOPTS=--junitxml=...``). :func:`pytest_collection_modifyitems`
#: runs them first: with ``--dist loadfile --no-loadscope-reorder`` the workers take whole
#: modules in this order, longest first, so the two finish together instead of one waiting on
#: a long module that came last (xdist's default order is by test count, which puts these
#: last).
MODULE_SECONDS = {
    "test_detect_train.py": 235, "test_cli_simulate.py": 200, "test_preintegration.py": 180,
    "test_pipeline_offsets.py": 160, "test_vio_corrupted_tracks.py": 145, "test_cli_calib.py": 135,
    "test_vio_marginalize.py": 115, "test_vio_estimator.py": 105, "test_pipeline_run.py": 100,
    "test_vio_solver.py": 80, "test_calib_train.py": 60, "test_calib_loop.py": 60,
    "test_detect_model.py": 60, "test_cli_vio.py": 55, "test_closed_loop.py": 50,
}


def pytest_collection_modifyitems(session, config, items):
    """Longest modules first (:data:`MODULE_SECONDS`); the order inside a module is kept."""
    items.sort(key=lambda item: -MODULE_SECONDS.get(item.path.name, 0))
