"""Options built from config fields (:mod:`uavcal_jax.argtypes`) and ``uavcal demo --set``."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field

import pytest

from uavcal_jax.argtypes import ConfigFlag, add_config_flags, field_docs, flag_overrides
from uavcal_jax.config import ConfigError, UnknownConfigKey, apply_overrides


@dataclass(frozen=True)
class _Inner:
    """Inner section.

    Attributes:
        rate_hz: samples per second (:data:`uavcal_jax.data.euroc_rig.EUROC_RATE_HZ`,
            ``200`` here).
    """

    rate_hz: float = 200.0


@dataclass(frozen=True)
class _Root:
    """Root.

    Attributes:
        size: ``(width, height)``.
        noise, blur: switch the :func:`~uavcal_jax.sim.sensor.apply` stage on.
        inner: the inner section.
        name: a name.

    Text after the section.
    """

    size: tuple[int, int] = (376, 240)
    noise: bool = True
    blur: bool = False
    inner: _Inner | None = field(default_factory=_Inner)
    name: str = "a"


FLAGS = (ConfigFlag("size"), ConfigFlag("noise"), ConfigFlag("blur"),
         ConfigFlag("inner.rate_hz", flag="--rate", type=float),
         ConfigFlag("inner", flag="--no-inner", const=None, help="drop the inner section"),
         ConfigFlag("name", choices=("a", "b")))


def test_field_docs_reads_the_attributes_section():
    docs = field_docs(_Root)
    assert docs == {"size": "(width, height).", "noise": "switch the apply stage on.",
                    "blur": "switch the apply stage on.", "inner": "the inner section.",
                    "name": "a name."}
    assert field_docs(_Inner) == {
        "rate_hz": "samples per second (uavcal_jax.data.euroc_rig.EUROC_RATE_HZ, 200 here)."}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_config_flags(parser, _Root, FLAGS)
    return parser


def test_flags_given_become_overrides_in_order():
    parser = _parser()
    assert flag_overrides(parser.parse_args([]), FLAGS) == {}  # defaults stay the config's
    args = parser.parse_args(["--name", "b", "--no-noise", "--blur", "--rate", "50"])
    got = flag_overrides(args, FLAGS)
    assert got == {"noise": False, "blur": True, "inner.rate_hz": 50.0, "name": "b"}
    assert list(got) == ["noise", "blur", "inner.rate_hz", "name"]  # FLAGS' order
    assert apply_overrides(_Root(), got) == _Root(noise=False, blur=True,
                                                  inner=_Inner(50.0), name="b")
    assert apply_overrides(_Root(), flag_overrides(parser.parse_args(["--no-inner"]), FLAGS)
                           ).inner is None
    with pytest.raises(SystemExit):
        parser.parse_args(["--name", "c"])


def test_help_states_doc_key_and_default():
    helps = {a.dest: a.help for a in _parser()._actions}
    assert helps["size"] == "(width, height). (--set size) [default: 376x240]"
    assert helps["inner__rate_hz"].endswith("(--set inner.rate_hz) [default: 200]")
    assert helps["noise"].startswith("sets noise to false; noise: switch the apply stage")
    assert helps["inner"] == "drop the inner section (--set inner=none)"


def test_demo_set_reaches_the_simulation_and_the_run():
    from uavcal_jax.commands.demo import DEMO_SIM, demo_configs
    from uavcal_jax.pipeline.run_config import RunConfig

    configs = demo_configs([])
    assert configs == {"sim": DEMO_SIM, "run": RunConfig()}
    configs = demo_configs(["sim.seed=3", "run.detect.every=2", "sim.imu_offset=none"], seed=5,
                           imu_offset=(0.1,) * 6)
    assert (configs["sim"].seed, configs["sim"].imu_offset) == (3, None)  # --set after both
    assert demo_configs([], seed=5, imu_offset=(0.1,) * 6)["sim"] == dataclasses.replace(
        DEMO_SIM, seed=5, imu_offset=(0.1,) * 6)
    assert configs["run"] == apply_overrides(RunConfig(), ["detect.every=2"])
    with pytest.raises(UnknownConfigKey, match="'sim.nope'.*sim.seed"):
        demo_configs(["sim.nope=1"])
    with pytest.raises(ConfigError, match="sim. .*run."):
        demo_configs(["seed=1"])
    with pytest.raises(ConfigError, match="sim: duration"):
        demo_configs(["sim.duration=0"])
