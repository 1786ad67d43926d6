"""Measure a real camera's noise curve and vignetting, and compare with the simulator's sensor.

Reads an EuRoC/ASL folder whose cam0/cam1 frames show a still scene (the rig standing still,
e.g. ``euroc_v101_micro``) and prints:

* per camera, the temporal noise curve (std against mean intensity, both estimators of
  :func:`uavcal_jax.sim.sensor_fit.noise_curve`) of the real frames and of the simulator's
  sensor (``sim.sensor``, default settings) given the real mean image as its noise-free
  signal, the same number of frames, and the shot + read fit of each;
* the frame-to-frame brightness fluctuation (std of the frame means);
* the stereo vignetting fit (:func:`uavcal_jax.sim.sensor_fit.stereo_vignetting`).

The last line is one JSON object with every number. Example::

    python experiments/camera_fit.py ../shared/data/euroc_v101_micro

``uavcal_jax.sim.config.EUROC_CAMERA_PRESET`` and ``sim.sensor``'s constants come from it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data.euroc import camera_calibration_from_yaml, find_mav0, read_sensor_yaml
from uavcal_jax.sim import sensor, sensor_fit
from uavcal_jax.sim.config import SimConfig, sensor_model


def _frames(folder: Path) -> np.ndarray:
    files = sorted((folder / "data").glob("*.png"))
    return np.stack([cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files])


def _fit_row(curve: sensor_fit.NoiseCurve) -> dict:
    fit = sensor_fit.fit_shot_read(curve)
    return {"mean_dn": np.round(curve.mean_dn, 1).tolist(),
            "std_dn": np.round(curve.std_dn, 3).tolist(),
            "dn_per_electron": round(fit.dn_per_electron, 5),
            "dn_per_electron_se": round(fit.slope_se, 5),
            "intercept_dn2": round(fit.intercept_dn2, 3),
            "intercept_se": round(fit.intercept_se, 3),
            "read_noise_electrons": round(fit.read_noise_electrons, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="EuRoC/ASL folder of a static recording")
    args = parser.parse_args()
    mav0 = find_mav0(args.root)
    model = sensor_model(SimConfig())
    frames, calibs, out = {}, {}, {"noise": {}}
    for cam in ("cam0", "cam1"):
        frames[cam] = _frames(mav0 / cam)
        calibs[cam] = camera_calibration_from_yaml(read_sensor_yaml(mav0 / cam / "sensor.yaml"),
                                                   mav0 / cam / "sensor.yaml")
        x = frames[cam]
        signal = jnp.asarray(x.astype(np.float64).mean(axis=0) / model.mean_dn(1.0), jnp.float32)
        sim = np.stack([np.asarray(sensor.sensor_image(signal, jax.random.PRNGKey(i), model))
                        for i in range(x.shape[0])])
        fm = x.mean(axis=(1, 2))
        out["noise"][cam] = {"frames": int(x.shape[0]), "mean_dn": round(float(x.mean()), 1),
                             "frame_mean_rel_std": round(float(fm.std() / fm.mean()), 4)}
        for est in sensor_fit.ESTIMATORS:
            for name, f in (("real", x), ("sim", sim)):
                row = _fit_row(sensor_fit.noise_curve(f, estimator=est, lo=20, hi=240,
                                                      bin_width=20))
                out["noise"][cam][f"{name}_{est}"] = row
                print(f"{cam} {est:10s} {name:4s} K {row['dn_per_electron']:.5f} DN/e- "
                      f"(+-{row['dn_per_electron_se']:.5f}), dark {row['intercept_dn2']:.3f} "
                      f"DN^2 (+-{row['intercept_se']:.3f}); std at mean: " + " ".join(
                          f"{m:.0f}:{s:.2f}" for m, s in zip(row["mean_dn"], row["std_dn"],
                                                            strict=True)))
    vig = sensor_fit.stereo_vignetting(frames["cam0"], frames["cam1"], calibs["cam0"],
                                       calibs["cam1"])
    out["vignetting"] = {"exponent": round(vig.exponent, 3), "exponent_se":
                         round(vig.exponent_se, 3), "log_gain_ratio":
                         round(vig.log_gain_ratio, 4), "pixels": vig.pixels}
    print(f"vignetting cos^p: p = {vig.exponent:.2f} +- {vig.exponent_se:.2f} "
          f"({vig.pixels} matched pixels; cam0/cam1 brightness {np.exp(vig.log_gain_ratio):.3f})")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
