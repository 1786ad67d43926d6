"""Rotor vibration in a simulated IMU: a spectrum measured on a real flight, and samples drawn
from it.

A real multirotor's IMU reads, on top of the motion the ground truth explains, the airframe's
vibration: broad humps at the rotors' (aliased) frequencies and structural modes, and a
broadband floor far above the sensor's own white noise. :func:`fit_vibration` measures them
from an IMU recording, in the band above the flight's motion (``f_low_hz``), as a
:class:`VibrationSpectrum`:

- bands: Gaussian-shaped humps in the one-sided power spectral density (PSD), each with a
  centre frequency, a width and, per IMU axis, the RMS it adds to the gyro and the
  accelerometer;
- floors: the broadband white density per axis that the IMU's own white noise
  (:class:`~uavcal_jax.imu.noise.ImuNoise`, which the simulator adds anyway) leaves unexplained,
  assumed flat at every frequency (it cannot be seen under the motion below ``f_low_hz``).

:func:`vibration_samples` draws vibration with that PSD as filtered Gaussian noise (white noise
shaped in the frequency domain): its expected PSD is the model's, so the bands' centre
frequencies and powers, and the band power above ``f_low_hz``, are reproduced.

Frequencies are those seen at the recording's rate: an ADIS16448 sampled at 200 Hz (EuRoC)
shows rotor harmonics above 100 Hz folded below it, and the bands are placed where they were
seen. At another rate, bands above its Nyquist frequency are dropped.

:data:`EUROC_V101_VIBRATION` is the spectrum of EuRoC V1_01's IMU in flight (what
``SimConfig.imu_vibration`` scales).

The rotors' speed sets the spectrum: standing on its support before take-off, the MAV idles
them, and V1_01's IMU then shows a hump near 19 Hz and a third of the flight's accelerometer
vibration (:data:`EUROC_V101_REST_VIBRATION`, measured on those seconds) instead of the folded
rotor harmonics near 95 Hz. :func:`rest_weight` tells the samples at rest from the trajectory
(no measurable motion: a flying multirotor never holds still to a centimetre for a second),
and :func:`mixed_vibration_samples` switches between the two spectra with the rotors' spool-up
time.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage, signal

from uavcal_jax.data.euroc import read_imu_folder
from uavcal_jax.data.euroc_format import MAV0
from uavcal_jax.imu.noise import ImuNoise

__all__ = [
    "EUROC_V101_REST_VIBRATION",
    "EUROC_V101_VIBRATION",
    "VibrationBand",
    "VibrationSpectrum",
    "fit_vibration",
    "fit_vibration_file",
    "imu_psd",
    "mixed_vibration_samples",
    "rest_weight",
    "vibration_samples",
]

#: Welch segment length (samples) of :func:`imu_psd`: 1024 at 200 Hz is 0.2 Hz bins, fine
#: enough for the humps (several Hz wide) and ~55 averages over V1_01's 145 s.
PSD_SEGMENT = 1024
#: Welch segment length (samples) for the few seconds at rest: 0.8 Hz bins, 6 averages over
#: V1_01's 4.7 s (1024-sample segments leave too few averages to tell a hump from noise).
REST_PSD_SEGMENT = 256
#: At rest (:func:`rest_weight`): over a centred window of ``REST_WINDOW_S`` seconds the
#: position spans under ``REST_SPAN_M`` metres on every axis and the angular rate stays under
#: ``REST_RATE_RADPS``. EuRoC's MAVs standing before take-off span 1-3 mm and 0.02 rad/s
#: (their ground truth's own noise); in flight, 7-35 cm and 0.2-0.6 rad/s over a second.
REST_WINDOW_S = 1.0
REST_SPAN_M = 0.01
REST_RATE_RADPS = 0.05
#: Seconds the rotors take to go from idle to flight speed (and back): the switch between
#: the two spectra is a ramp this long (a moving average of the at-rest flag).
SPOOL_S = 0.5


@dataclass(frozen=True)
class VibrationBand:
    """One hump of the vibration PSD.

    Attributes:
        freq_hz: centre frequency (Hz).
        sigma_hz: its spread (Hz), a Gaussian's standard deviation in frequency.
        gyro_rms: (3,) rad/s, the RMS this band adds to the gyro's x, y, z (IMU frame).
        accel_rms: (3,) m/s^2, the RMS it adds to the accelerometer's x, y, z.
    """

    freq_hz: float
    sigma_hz: float
    gyro_rms: tuple[float, float, float]
    accel_rms: tuple[float, float, float]


@dataclass(frozen=True)
class VibrationSpectrum:
    """A vibration model: bands plus a broadband floor (see the module docstring).

    Attributes:
        bands: the humps.
        gyro_floor: (3,) rad/s/sqrt(Hz), the white density per axis beyond the IMU model's
            white noise (Kalibr's continuous-time convention, as ``gyroscope_noise_density``:
            a sample at period ``dt`` has std ``density / sqrt(dt)``).
        accel_floor: (3,) m/s^2/sqrt(Hz), likewise.
        f_low_hz: the lower edge of the band it was measured in (Hz).
        rate_hz: the sample rate it was measured at (Hz).
    """

    bands: tuple[VibrationBand, ...]
    gyro_floor: tuple[float, float, float]
    accel_floor: tuple[float, float, float]
    f_low_hz: float
    rate_hz: float

    def to_dict(self) -> dict:
        """JSON-ready values (``sim_config.json``)."""
        return asdict(self)


#: EuRoC V1_01_easy's IMU (ADIS16448 at 200 Hz, the whole 145 s in flight), above 15 Hz: a
#: hump at 17.2 Hz (gyro y/z, accel x), one at 27.3 Hz (gyro x, accel y), smaller ones at 55.4
#: and 72.7 Hz, and the folded rotor harmonics at 93.6 and 96.9 Hz (all axes, accel x/z
#: strongest); the accel floors are 10-19x the ``sensor.yaml`` white density, the gyro floors
#: 2.4-5x. Measured by
#:     python -c "from uavcal_jax.sim.imu_vibration import fit_vibration_file as f; \
#:                print(f('../shared/data/euroc_v101_micro'))"
#: (rounded to 4 digits; ``tests/test_imu_vibration.py`` re-measures it when the data is there).
EUROC_V101_VIBRATION = VibrationSpectrum(
    bands=(
        VibrationBand(freq_hz=17.15, sigma_hz=1.283,
                      gyro_rms=(0.006792, 0.01753, 0.01392),
                      accel_rms=(0.1509, 0.04773, 0.01103)),
        VibrationBand(freq_hz=27.25, sigma_hz=1.073,
                      gyro_rms=(0.01406, 0.003479, 0.008516),
                      accel_rms=(0.05686, 0.2366, 0.05742)),
        VibrationBand(freq_hz=55.4, sigma_hz=0.9515,
                      gyro_rms=(0.0008867, 0.002108, 0.001673),
                      accel_rms=(0.09037, 0.02286, 0.06652)),
        VibrationBand(freq_hz=72.74, sigma_hz=0.6216,
                      gyro_rms=(0.0009329, 0.007039, 0.002542),
                      accel_rms=(0.2139, 0.1024, 0.1313)),
        VibrationBand(freq_hz=93.61, sigma_hz=4.19,
                      gyro_rms=(0.00731, 0.03039, 0.01604),
                      accel_rms=(0.6892, 0.3011, 0.5362)),
        VibrationBand(freq_hz=96.88, sigma_hz=0.8374,
                      gyro_rms=(0.003625, 0.02192, 0.007702),
                      accel_rms=(0.5833, 0.1465, 0.5257)),
    ),
    gyro_floor=(0.0004094, 0.0008846, 0.0005844),
    accel_floor=(0.03794, 0.01957, 0.02514),
    f_low_hz=15.0, rate_hz=200.0,
)


#: EuRoC V1_01_easy's IMU standing before take-off, rotors idling (its first 4.4 s, 881
#: samples, where :func:`rest_weight` is 1; the rotors spool up in the 0.3 s after, the MAV
#: lifts off at 4.7 s): humps at 17.6 and 18.8 Hz (gyro x, accel y strongest), 27.3, 32.1,
#: 47.2 and 74.5 Hz (accel x); half the flight's accelerometer vibration and no folded rotor
#: harmonics near 95 Hz. The real vibration is not steady while it stands: strongest in the
#: first 1.5 s (accel y 0.6-1.2 m/s^2 RMS over half seconds), 0.15-0.25 after; this is its
#: mean. Measured by
#:     python -c "from uavcal_jax.sim.imu_vibration import fit_vibration_file as f; \
#:                print(f('../shared/data/euroc_v101_micro', rest=True))"
#: (rounded to 4 digits; ``tests/test_imu_vibration.py`` re-measures it when the data is there).
EUROC_V101_REST_VIBRATION = VibrationSpectrum(
    bands=(
        VibrationBand(freq_hz=17.56, sigma_hz=0.7812,
                      gyro_rms=(0.03103, 0.003727, 0.004351),
                      accel_rms=(0.02894, 0.3404, 0.0358)),
        VibrationBand(freq_hz=18.8, sigma_hz=2.117,
                      gyro_rms=(0.03611, 0.004174, 0.009118),
                      accel_rms=(0.04479, 0.479, 0.04998)),
        VibrationBand(freq_hz=27.31, sigma_hz=0.7812,
                      gyro_rms=(0.01176, 0.003908, 0.004466),
                      accel_rms=(0.04668, 0.2068, 0.03645)),
        VibrationBand(freq_hz=32.08, sigma_hz=0.7812,
                      gyro_rms=(0.01269, 0.004737, 0.00404),
                      accel_rms=(0.06785, 0.2529, 0.05111)),
        VibrationBand(freq_hz=47.24, sigma_hz=1.237,
                      gyro_rms=(0.003109, 0.003838, 0.002651),
                      accel_rms=(0.08615, 0.08568, 0.04298)),
        VibrationBand(freq_hz=74.51, sigma_hz=1.616,
                      gyro_rms=(0.001185, 0.005843, 0.002725),
                      accel_rms=(0.1597, 0.03029, 0.06202)),
    ),
    gyro_floor=(7.753e-05, 0.0004531, 0.0003026),
    accel_floor=(0.01075, 0.004993, 0.006284),
    f_low_hz=15.0, rate_hz=200.0,
)


def imu_psd(samples: np.ndarray, rate_hz: float, nperseg: int = PSD_SEGMENT
            ) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD of (N, C) samples per column (linear detrend per segment).

    Returns:
        ``(f, psd)``: (F,) Hz and (F, C) in units^2/Hz (a white noise of Kalibr density ``d``
        reads ``2 d^2``).
    """
    samples = np.asarray(samples, dtype=np.float64)
    f, p = signal.welch(samples, fs=rate_hz, nperseg=min(nperseg, len(samples)), axis=0,
                        detrend="linear")
    return f, p


def fit_vibration(gyro: np.ndarray, accel: np.ndarray, rate_hz: float, noise: ImuNoise, *,
                  f_low_hz: float = 15.0, max_bands: int = 6, floor_percentile: float = 20.0,
                  nperseg: int = PSD_SEGMENT) -> VibrationSpectrum:
    """The vibration spectrum of an IMU recording in flight, above the motion's band.

    Per channel (gyro x, y, z, accel x, y, z) the PSD above ``f_low_hz`` is split into a floor
    (its ``floor_percentile``-th percentile) and the excess over it. The excesses, each in
    units of its floor and summed over the channels, smoothed over 2 Hz, locate the humps:
    the ``max_bands`` most prominent peaks (prominence above one floor). The band between two
    peaks is split at the lowest point between them; each band's frequency and spread are its
    mean frequency over its peak's top half and the half-power width (as a Gaussian's), and its
    RMS per channel is the square root of the excess integrated over it (so the band power
    above ``f_low_hz`` is kept). The floors less the white noise of ``noise`` (``2 d^2``) are
    the broadband densities.

    Args:
        gyro, accel: (N, 3) samples (rad/s, m/s^2) at a constant ``rate_hz``, in flight.
        rate_hz: sample rate (Hz).
        noise: the IMU's own noise model, whose white noise the simulator adds separately.
        f_low_hz: lower edge of the band measured (Hz): above the flight's motion.
        max_bands: at most this many humps.
        floor_percentile: percentile of each channel's PSD taken as its floor.
        nperseg: Welch segment length (samples): shorter for a short recording (coarser bins,
            more averages).

    Raises:
        ValueError: fewer than 3 segments' length of samples (5 half-overlapping Welch
            segments), or ``f_low_hz`` not below Nyquist.
    """
    x = np.concatenate([np.asarray(gyro, np.float64), np.asarray(accel, np.float64)], axis=1)
    if x.ndim != 2 or x.shape[1] != 6 or len(x) < 3 * nperseg:
        raise ValueError(f"need (N, 3) gyro and accel with N >= {3 * nperseg} samples")
    if not 0 < f_low_hz < rate_hz / 2:
        raise ValueError(f"f_low_hz must lie in (0, {rate_hz / 2:g}) Hz, got {f_low_hz}")
    f, p = imu_psd(x, rate_hz, nperseg)
    df = float(f[1] - f[0])
    band = f >= f_low_hz
    f, p = f[band], p[band]
    floor = np.percentile(p, floor_percentile, axis=0)
    excess = np.maximum(p - floor, 0.0)
    smooth = max(1, int(round(2.0 / df)))
    relative = np.divide(excess, floor, out=np.zeros_like(excess), where=floor > 0)
    score = np.convolve(relative.sum(axis=1), np.ones(smooth) / smooth, mode="same")
    peaks, props = signal.find_peaks(score, prominence=1.0)
    peaks = np.sort(peaks[np.argsort(props["prominences"])[::-1][:max_bands]])
    bands = []
    if len(peaks):
        # band edges: the band's ends and the lowest point between neighbouring peaks
        edges = [0] + [a + int(np.argmin(score[a:b])) for a, b in zip(peaks[:-1], peaks[1:],
                                                                       strict=True)] + [len(f)]
        width, _, left, right = signal.peak_widths(score, peaks, rel_height=0.5)
        for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            # centre and width from the hump's top half (the excess elsewhere is noise about
            # the floor); the smoothing's variance is taken off the width
            a, b = int(np.ceil(left[i])), int(np.floor(right[i])) + 1
            mean = float(np.sum(score[a:b] * f[a:b]) / np.sum(score[a:b]))
            var = (width[i] * df / 2.3548) ** 2 - (smooth * df) ** 2 / 12.0
            # power: all the excess between the neighbouring humps (the band power is kept)
            rms = np.sqrt(excess[lo:hi].sum(axis=0) * df)
            bands.append(VibrationBand(freq_hz=mean, sigma_hz=float(np.sqrt(max(var, df ** 2))),
                                       gyro_rms=tuple(float(v) for v in rms[:3]),
                                       accel_rms=tuple(float(v) for v in rms[3:])))
    white = np.concatenate([np.broadcast_to(np.asarray(d, np.float64), (3,)) for d in
                            (noise.gyro_noise_density, noise.accel_noise_density)])
    extra = np.sqrt(np.maximum(floor - 2.0 * white ** 2, 0.0) / 2.0)
    return VibrationSpectrum(bands=tuple(bands),
                             gyro_floor=tuple(float(v) for v in extra[:3]),
                             accel_floor=tuple(float(v) for v in extra[3:]),
                             f_low_hz=float(f_low_hz), rate_hz=float(rate_hz))


def fit_vibration_file(root: str | Path, *, rest: bool = False, **kwargs) -> VibrationSpectrum:
    """:func:`fit_vibration` of an EuRoC/ASL folder's ``imu0`` (its ``sensor.yaml`` gives the
    rate and the noise model).

    Args:
        root: the folder (holding ``mav0``, or ``mav0`` itself).
        rest: ``False``: the whole recording, which should be in flight. ``True``: the samples
            the simulator would take as at rest (:func:`rest_weight` 1 along a trajectory
            fitted to the folder's ground truth: standing, rotors idling, before they spool
            up for take-off), with ``nperseg`` :data:`REST_PSD_SEGMENT`.
        kwargs: :func:`fit_vibration`'s options.
    """
    root = Path(root)
    mav0 = root if root.name == MAV0 else root / MAV0
    imu, calib = read_imu_folder(mav0 / "imu0")
    gyro, accel = imu.gyro, imu.accel
    if rest:
        keep = _at_rest(mav0, imu.t_ns, calib.rate_hz)
        gyro, accel = gyro[keep], accel[keep]
        kwargs = {"nperseg": REST_PSD_SEGMENT} | kwargs
    return fit_vibration(gyro, accel, calib.rate_hz, calib.noise, **kwargs)


def _at_rest(mav0: Path, t_ns: np.ndarray, rate_hz: float) -> np.ndarray:
    """(N,) bool: the IMU stamps ``t_ns`` inside the first stretch at rest of ``mav0``'s ground
    truth (where :func:`rest_weight` is 1)."""
    from uavcal_jax.data.euroc import read_ground_truth_csv  # needed here only
    from uavcal_jax.sim.trajectory_fit import fit_tum_trajectory

    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    traj = fit_tum_trajectory(read_ground_truth_csv(gt_csv))
    inside = (t_ns >= traj.t_start * 1e9) & (t_ns <= traj.t_end * 1e9)
    state = traj.state_ns(t_ns[inside])
    still = rest_weight(state.position, state.angular_velocity_body, rate_hz) >= 1.0 - 1e-9
    if not still.any():
        raise ValueError(f"{mav0}: the ground truth never rests")
    start = int(np.argmax(still))
    run = still[start:]
    end = start + (int(np.argmin(run)) if not run.all() else len(run))
    keep = np.zeros(len(t_ns), bool)
    keep[np.flatnonzero(inside)[start:end]] = True
    return keep


def rest_weight(position: np.ndarray, angular_rate: np.ndarray, rate_hz: float) -> np.ndarray:
    """How far each sample is into the rotors' idle state: (N,) in [0, 1], 1 at rest.

    A sample is at rest when the centred :data:`REST_WINDOW_S` window around it spans under
    :data:`REST_SPAN_M` on every position axis and its angular rate stays under
    :data:`REST_RATE_RADPS` (the module docstring). The flag is smoothed by a centred moving
    average over :data:`SPOOL_S`, so the spectrum ramps as the rotors spool up.

    Args:
        position: (N, 3) metres, any fixed frame, at the samples (equally spaced).
        angular_rate: (N, 3) rad/s, at the same samples.
        rate_hz: the samples' rate (Hz).
    """
    position = np.asarray(position, np.float64)
    window = max(1, int(round(REST_WINDOW_S * rate_hz)))
    span = (ndimage.maximum_filter1d(position, window, axis=0, mode="nearest")
            - ndimage.minimum_filter1d(position, window, axis=0, mode="nearest")).max(axis=1)
    rate = ndimage.maximum_filter1d(np.linalg.norm(angular_rate, axis=1), window,
                                    mode="nearest")
    still = ((span < REST_SPAN_M) & (rate < REST_RATE_RADPS)).astype(np.float64)
    return ndimage.uniform_filter1d(still, max(1, int(round(SPOOL_S * rate_hz))),
                                    mode="nearest")


def mixed_vibration_samples(flight: VibrationSpectrum, rest: VibrationSpectrum,
                            weight: np.ndarray, rate_hz: float, rng_flight: np.random.Generator,
                            rng_rest: np.random.Generator, scale: float = 1.0
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Vibration switching between two spectra: ``(1 - w) flight + w rest`` per sample.

    Each spectrum's samples come from its own generator (:func:`vibration_samples`); where
    ``weight`` is 0 everywhere the result is exactly the flight's samples, and the rest's
    generator is not drawn from. The two are independent, so midway through a ramp the power
    dips to half their mean (for the ramp's 0.5 s).

    Args:
        flight, rest: the spectra in flight and at rest.
        weight: (N,) in [0, 1], :func:`rest_weight`.
        rate_hz: the sample rate (Hz).
        rng_flight, rng_rest: each spectrum's generator.
        scale: both spectra's amplitudes times this.

    Returns:
        ``(gyro, accel)``, each (N, 3): rad/s and m/s^2.
    """
    weight = np.asarray(weight, np.float64)
    n = len(weight)
    gyro, accel = vibration_samples(flight, n, rate_hz, rng_flight, scale)
    if not weight.any():
        return gyro, accel
    rest_gyro, rest_accel = vibration_samples(rest, n, rate_hz, rng_rest, scale)
    w = weight[:, None]
    return (1.0 - w) * gyro + w * rest_gyro, (1.0 - w) * accel + w * rest_accel


def _model_psd(spectrum: VibrationSpectrum, f: np.ndarray, rate_hz: float) -> np.ndarray:
    """(F, 6) one-sided PSD of the model at ``f`` (Hz) for samples at ``rate_hz``: each band a
    Gaussian normalised to its power over ``[0, rate_hz / 2]``, plus the floors."""
    floor = 2.0 * np.square(np.array(spectrum.gyro_floor + spectrum.accel_floor))
    out = np.broadcast_to(floor, (len(f), 6)).copy()
    df = float(f[1] - f[0]) if len(f) > 1 else rate_hz / 2
    for b in spectrum.bands:
        if b.freq_hz >= rate_hz / 2:
            continue  # beyond this rate's Nyquist frequency
        shape = np.exp(-0.5 * ((f - b.freq_hz) / b.sigma_hz) ** 2)
        area = shape.sum() * df
        power = np.square(np.array(b.gyro_rms + b.accel_rms))
        out += shape[:, None] * (power / area)[None, :]
    return out


def vibration_samples(spectrum: VibrationSpectrum, n: int, rate_hz: float,
                      rng: np.random.Generator, scale: float = 1.0
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Vibration for ``n`` samples at ``rate_hz``: Gaussian noise with the model's PSD (each of
    the 6 channels independent), amplitudes times ``scale``.

    White unit-variance noise is shaped in the frequency domain by ``sqrt(S(f) rate / 2)``
    (one ``rfft`` of all ``n`` samples), so the result's expected one-sided PSD is ``scale^2
    S(f)``.

    Returns:
        ``(gyro, accel)``, each (n, 3): rad/s and m/s^2 to add to the exact measurements.
    """
    white = rng.normal(size=(n, 6))
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    gain = np.sqrt(_model_psd(spectrum, f, rate_hz) * rate_hz / 2.0) * scale
    out = np.fft.irfft(np.fft.rfft(white, axis=0) * gain, n=n, axis=0)
    return out[:, :3], out[:, 3:]

