"""Cached simulations: rendered once, reused, a changed setting renders a new folder, a
killed render leaves nothing that is mistaken for a recording; the calibrator's simulated
sets cover each trajectory within its span."""

import json

import pytest
from conftest import SHARED_DATA, shared_path

from uavcal_jax.data.tum import read_tum
from uavcal_jax.sim.cache import cached_simulation, config_tag
from uavcal_jax.sim.config import SimConfig
from uavcal_jax.sim.training_sets import SimSetConfig, sequence_configs

TINY = SimConfig(duration=0.3, resolution=(32, 24), camera_rate_hz=10, depth=False,
                 targets=False, seed=3)


def test_rendered_once_then_reused_and_keyed_by_config(tmp_path):
    first = cached_simulation(TINY, tmp_path, "tiny", progress=False)
    stamp = (first / "sim_config.json").stat().st_mtime_ns
    again = cached_simulation(TINY, tmp_path, "tiny", progress=False)
    assert again == first and (again / "sim_config.json").stat().st_mtime_ns == stamp
    assert json.loads((first / "sim_config.json").read_text())["config"]["seed"] == 3
    # speed knobs do not change the output, so they share the folder; a seed does not
    assert config_tag(SimConfig(**{**TINY.to_dict(), "resolution": (32, 24),
                                   "png_workers": 1})) == config_tag(TINY)
    other = SimConfig(**{**TINY.to_dict(), "resolution": (32, 24), "seed": 4})
    assert cached_simulation(other, tmp_path, "tiny", progress=False) != first


def test_a_later_field_off_keeps_the_tag_and_the_realistic_defaults_change_it():
    """``imu_rotation_deg`` and the realism options came after caches were tagged: off (as
    every recording before them was), the tag is the hash of the other fields (the folders
    written before stay valid); set, or at the realistic defaults, it is another folder."""
    import dataclasses
    import hashlib

    from uavcal_jax.sim.config import IDEAL_SENSORS

    ideal = dataclasses.replace(TINY, **IDEAL_SENSORS)
    later = ("imu_rotation_deg", "vignetting", "auto_exposure", "ae_target_dn",
             "ae_time_constant_s", "line_delay_s", "imu_vibration", "imu_scale",
             "imu_misalignment", "imu_g_sensitivity", "imu_time_offset",
             "imu_rest_vibration", "rotor_drag", "thrust_tilt_deg")
    fields = {k: v for k, v in ideal.to_dict().items()
              if k not in ("png_workers", "batch_size", *later)}
    before = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:8]
    assert config_tag(ideal) == before
    assert config_tag(TINY) != before  # EuRoC's realism is on by default
    turned = dataclasses.replace(ideal, imu_rotation_deg=(0.0, -90.0, 0.0))
    assert config_tag(turned) != before
    assert config_tag(dataclasses.replace(ideal, vignetting=1.1)) != before
    assert config_tag(dataclasses.replace(ideal, imu_vibration=1.0)) != before
    assert config_tag(dataclasses.replace(ideal, rotor_drag=0.4)) != before
    assert config_tag(dataclasses.replace(ideal, thrust_tilt_deg=(1.0, 0.0))) != before
    # the spectrum at rest changes a recorded flight's tag, never a planned flight's (where it
    # has no effect): the procedural caches stay valid
    planned = dataclasses.replace(TINY, imu_rest_vibration=False)
    assert config_tag(TINY) == config_tag(planned)
    recorded = dataclasses.replace(TINY, trajectory="flight.txt")
    assert config_tag(recorded) != config_tag(dataclasses.replace(recorded,
                                                                  imu_rest_vibration=False))


def test_a_killed_render_is_not_reused(tmp_path):
    out = tmp_path / f"tiny_{config_tag(TINY)}"
    (out / "mav0").mkdir(parents=True)  # a folder without sim_config.json: not complete
    root = cached_simulation(TINY, tmp_path, "tiny", progress=False)
    assert root == out and (root / "sim_config.json").is_file()
    assert not list(tmp_path.glob(".*partial"))


@pytest.mark.parametrize("family", ["euroc", "uzh_fpv"])
def test_trajectory_sets_cover_each_trajectory(family):
    folder = shared_path("trajectories", family)
    configs = sequence_configs(SimSetConfig(family=family), SHARED_DATA)
    assert [n for n, _ in configs] == sorted(p.stem for p in folder.glob("*.txt"))
    for _, cfg in configs:
        gt = read_tum(cfg.trajectory)
        span = (gt.t_ns[-1] - gt.t_ns[0]) * 1e-9
        assert span - 0.2 <= cfg.duration <= span
    capped = sequence_configs(SimSetConfig(family=family, max_duration=5.0), SHARED_DATA)
    assert all(cfg.duration == 5.0 for _, cfg in capped)
    with pytest.raises(ValueError, match="unknown"):
        sequence_configs(SimSetConfig(family=family, sequences=("nope",)), SHARED_DATA)


def test_realistic_airframes_are_drawn_per_flight_and_ideal_ones_stay_as_they_were():
    """``airframes="realistic"``: each procedural flight draws its rotor drag, thrust tilt
    and IMU mounting tilt from its seed (the same on every call, within the ranges); the ideal
    set's flights keep their configuration (and so their cached folders)."""
    from uavcal_jax.sim.training_sets import REALISTIC_AIRFRAME

    real = sequence_configs(SimSetConfig(family="procedural", count=6, max_duration=5,
                                         airframes="realistic"))
    again = sequence_configs(SimSetConfig(family="procedural", count=6, max_duration=5,
                                          airframes="realistic"))
    assert real == again
    lo, hi = REALISTIC_AIRFRAME["rotor_drag"]
    assert all(lo <= c.rotor_drag <= hi for _, c in real)
    assert len({c.rotor_drag for _, c in real}) == 6
    assert all(max(map(abs, c.thrust_tilt_deg)) < 5.0 and len(c.imu_rotation_deg) == 3
               for _, c in real)
    ideal = sequence_configs(SimSetConfig(family="procedural", count=6, max_duration=5))
    assert all(c.rotor_drag == 0.0 and c.thrust_tilt_deg is None and c.imu_rotation_deg is None
               for _, c in ideal)
    with pytest.raises(ValueError, match="airframes"):
        SimSetConfig(family="procedural", airframes="bent")
