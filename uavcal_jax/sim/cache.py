"""Simulated recordings rendered once and reused: a folder per configuration.

Sweeps (calibrator protocols and ablations, VIO tables) read the same simulated sequences many
times; rendering them is the slow part. :func:`cached_simulation` keys a folder by a name and
a hash of the full :class:`~uavcal_jax.sim.config.SimConfig`, so a changed setting renders a
new folder instead of silently reusing a stale one, and writes it atomically (simulated into
a temporary sibling, renamed when complete): a sweep killed mid-render leaves no half
sequence behind, and a rerun renders only what is missing.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from uavcal_jax.data.sim_config import SIM_CONFIG_FILE
from uavcal_jax.data.tum import read_tum
from uavcal_jax.sim import auto_exposure as ae
from uavcal_jax.sim.config import IDEAL_SENSORS, SimConfig
from uavcal_jax.sim.simulate import simulate

__all__ = ["cached_simulation", "config_tag", "trajectory_span"]


#: SimConfig fields added after caches were tagged, and the value each had before (off): a
#: field at that value is left out of the tag, so that older caches keep theirs. The realism
#: options' defaults are now on, so a default configuration tags differently from an old one.
_LATER_FIELDS = {"imu_rotation_deg": None, "ae_target_dn": ae.AE_TARGET_DN,
                 "ae_time_constant_s": ae.AE_TIME_CONSTANT_S, "imu_rest_vibration": False,
                 "rotor_drag": 0.0, "thrust_tilt_deg": None,
                 **IDEAL_SENSORS}


def config_tag(config: SimConfig) -> str:
    """8 hex digits identifying every field of ``config`` (the ``png_workers`` and
    ``batch_size`` speed knobs excluded: they do not change the output)."""
    fields = {k: v for k, v in config.to_dict().items() if k not in ("png_workers",
                                                                      "batch_size")}
    if fields.get("trajectory"):
        fields["trajectory"] = Path(fields["trajectory"]).name
    for later, off in _LATER_FIELDS.items():  # added since caches were written: off, the
        if fields.get(later) == off:                # tag stays what it was
            fields.pop(later, None)
    if not (config.trajectory and config.imu_vibration):  # no effect on a planned flight
        fields.pop("imu_rest_vibration", None)
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
