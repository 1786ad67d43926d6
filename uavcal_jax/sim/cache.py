"""Simulated recordings rendered once and reused: a folder per configuration.

Sweeps (calibrator protocols and ablations, VIO tables) read the same simulated sequences many
times; rendering them is the slow part. :func:`cached_simulation` keys a folder by a name and
a hash of the full :class:`~uavcal_jax.sim.config.SimConfig`, so a changed setting renders a
new folder instead of silently reusing a stale one, and writes it atomically (simulated into
a temporary sibling, renamed when complete): a sweep killed mid-render leaves no half
sequence behind, and a rerun renders only what is missing.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

from uavcal_jax.data.sim_config import SIM_CONFIG_FILE
from uavcal_jax.data.tum import read_tum
from uavcal_jax.sim.config import IMU_ERRORS, SimConfig
from uavcal_jax.sim.simulate import simulate

__all__ = ["cached_simulation", "config_tag", "trajectory_span"]


#: SimConfig fields added after caches were tagged, left out of the tag while at their
#: defaults (off).
_LATER_FIELDS = ("imu_rotation_deg", "vignetting", "auto_exposure", "ae_target_dn",
                 "ae_time_constant_s", "line_delay_s", *IMU_ERRORS)
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(SimConfig)}


def config_tag(config: SimConfig) -> str:
    """8 hex digits identifying every field of ``config`` (the ``png_workers`` and
    ``batch_size`` speed knobs excluded: they do not change the output)."""
    fields = {k: v for k, v in config.to_dict().items() if k not in ("png_workers",
                                                                      "batch_size")}
    if fields.get("trajectory"):
        fields["trajectory"] = Path(fields["trajectory"]).name
    for later in _LATER_FIELDS:  # added since caches were written: unset, they keep the tag
        if fields.get(later) == _DEFAULTS[later]:
            fields.pop(later, None)
    text = json.dumps(fields, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def trajectory_span(path: str | Path) -> float:
    """Seconds from a TUM trajectory file's first to its last pose."""
    gt = read_tum(path)
    return float((gt.t_ns[-1] - gt.t_ns[0]) * 1e-9)


def cached_simulation(config: SimConfig, cache: str | Path, name: str, *,
                      progress: bool = True) -> Path:
    """The folder of ``config``'s recording under ``cache`` (``cache/<name>_<tag>``),
    simulated first if it is not there yet."""
    out = Path(cache) / f"{name}_{config_tag(config)}"
    if (out / "mav0").is_dir() and (out / SIM_CONFIG_FILE).is_file():
        return out
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    simulate(config, tmp, progress=progress)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return out
