"""The allocator switch the CLI makes (uavcal_jax.allocator): a freed large block is reused
without new page faults, and the switch can be turned off. Each case runs in a fresh
interpreter, since the switch is process-wide."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

# malloc, touch, free and malloc + touch again a 64 MiB block (plain malloc: numpy would ask
# for huge pages); print the second allocation's page faults.
_PROBE = """
import ctypes, ctypes.util, resource, sys
from uavcal_jax.allocator import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
size = 1 << 26
block = libc.malloc(size); ctypes.memset(block, 1, size); libc.free(block)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
block = libc.malloc(size); ctypes.memset(block, 1, size)
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
PAGES = (1 << 26) // 4096  # the block's 4 KiB pages


def _probe(mode: str, **env) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True,
                         check=True, env={**os.environ, **env}).stdout.split()
    return out[0], int(out[1])


pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc",
                                reason="the switch is glibc's; elsewhere it does nothing")


def test_freed_block_is_reused_without_page_faults():
    _, default_faults = _probe("default")
    applied, kept_faults = _probe("keep")
    assert applied == "True"
    # glibc's default maps the block afresh: every page faults again
    assert default_faults > PAGES // 2
    assert kept_faults < PAGES // 50


def test_switch_can_be_turned_off():
    applied, faults = _probe("keep", UAVCAL_KEEP_FREED_MEMORY="0")
    assert applied == "False"
    assert faults > PAGES // 2
