"""Shared fixtures: the real-data folder beside the checkout, and float64 JAX."""

from __future__ import annotations

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


@pytest.fixture(scope="session")
def xla_cache(tmp_path_factory):
    """A session-wide persistent XLA compilation cache, so identical computations compiled by
    several tests (detector training steps, say) compile once."""
    from jax.experimental.compilation_cache import compilation_cache as cc

    if not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir",
                          str(tmp_path_factory.getbasetemp() / "xla_cache"))
        cc.reset_cache()
    yield
