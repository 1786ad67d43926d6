"""Road vehicles as real fleets have them: body kinds, sizes, cabin layouts and paint colours.

Every vehicle is one yaw box (the renderer's solid) labelled ``car`` (a detector maps truck,
bus and minibus to car); its kind sets the box's size and where the textures paint glass,
roof, cargo box and wheels (:func:`uavcal_jax.sim.textures.face_atlas`). Kinds and their
shares (:data:`KINDS`) follow a European street: mostly sedans, hatchbacks and SUVs, some
vans, a few trucks and buses. Paint colours (:data:`PAINTS`) follow the published world
shares of new cars (white, black, grey and silver about three quarters; blue and red most of
the rest; a few beige, green, yellow and orange ones).

Lengths along the box's local x (forward, +x is the front), metres; cabin positions are
fractions of the length measured from the rear (0) to the front (1).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["KINDS", "PASSENGER_KINDS", "PAINTS", "Vehicle", "draw_paint", "draw_vehicle",
           "vehicle_of_size"]


@dataclasses.dataclass(frozen=True)
class Kind:
    """One body kind.

    Attributes:
        name: e.g. ``"sedan"``.  share: its share of a street's vehicles.
        length, width, height: (min, max) metres.
        glass: ``(rear window start, roof start, roof end, windshield end)`` as fractions of
            the length from the rear: rear window, roof and windshield seen from above; the
            side windows span ``[glass[0], glass[3]]``.
        cargo: the rear part up to this fraction is a cargo box, brighter than the cab
            (trucks), 0 for none.
    """

    name: str
    share: float
    length: tuple[float, float]
    width: tuple[float, float]
    height: tuple[float, float]
    glass: tuple[float, float, float, float]
    cargo: float = 0.0


KINDS: tuple[Kind, ...] = (
    Kind("sedan", 0.34, (4.3, 5.0), (1.75, 1.9), (1.40, 1.50), (0.14, 0.24, 0.55, 0.68)),
    Kind("hatchback", 0.28, (3.7, 4.3), (1.65, 1.80), (1.45, 1.55), (0.04, 0.10, 0.56, 0.70)),
    Kind("suv", 0.22, (4.4, 5.0), (1.80, 2.00), (1.60, 1.80), (0.03, 0.08, 0.62, 0.72)),
    Kind("van", 0.09, (4.8, 6.0), (1.90, 2.10), (1.90, 2.60), (0.02, 0.03, 0.80, 0.88)),
    Kind("truck", 0.04, (6.5, 10.0), (2.20, 2.50), (2.80, 3.60), (0.74, 0.76, 0.90, 0.93),
         cargo=0.72),
    Kind("bus", 0.03, (10.0, 12.0), (2.45, 2.55), (2.90, 3.30), (0.02, 0.02, 0.97, 0.99)),
)
#: Kinds no taller than a person (1.9 m): the halls' targets, which must not reach the drone.
PASSENGER_KINDS: tuple[str, ...] = ("sedan", "hatchback", "suv")

#: ``(name, share, RGB in [0, 1])`` of body paints.
PAINTS: tuple[tuple[str, float, tuple[float, float, float]], ...] = (
    ("white", 0.26, (0.93, 0.93, 0.91)),
    ("black", 0.20, (0.06, 0.06, 0.07)),
    ("grey", 0.17, (0.40, 0.41, 0.43)),
    ("silver", 0.13, (0.68, 0.69, 0.71)),
    ("blue", 0.09, (0.10, 0.20, 0.55)),
    ("red", 0.08, (0.70, 0.07, 0.06)),
    ("beige", 0.03, (0.72, 0.64, 0.50)),
    ("green", 0.02, (0.10, 0.35, 0.15)),
    ("yellow", 0.01, (0.93, 0.75, 0.08)),
    ("orange", 0.01, (0.88, 0.40, 0.06)),
)


@dataclasses.dataclass(frozen=True)
class Vehicle:
    """One drawn vehicle.

    Attributes:
        kind: its :class:`Kind`.  half: (3,) half length, width, height, metres.
        paint: index into :data:`PAINTS`.  color: (3,) RGB body colour in [0, 1] (a truck's
        cab is painted a darker shade of it than its cargo box).
    """

    kind: Kind
    half: np.ndarray
    paint: int
    color: np.ndarray


def draw_paint(rng: np.random.Generator) -> tuple[int, np.ndarray]:
    """A paint index (by :data:`PAINTS`' shares) and its RGB, brightness jittered +-8 %."""
    shares = np.array([p[1] for p in PAINTS])
    i = int(rng.choice(len(PAINTS), p=shares / shares.sum()))
    rgb = np.clip(np.array(PAINTS[i][2]) * rng.uniform(0.92, 1.08), 0.0, 1.0)
    return i, rgb


def draw_vehicle(rng: np.random.Generator, kinds: tuple[str, ...] | None = None) -> Vehicle:
    """A vehicle of one of ``kinds`` (names; ``None``: all of :data:`KINDS`), drawn by their
    shares, with a size uniform in the kind's ranges and a paint from :func:`draw_paint`."""
    pool = [k for k in KINDS if kinds is None or k.name in kinds]
    if not pool:
        raise ValueError(f"no vehicle kind among {kinds}")
    shares = np.array([k.share for k in pool])
    kind = pool[int(rng.choice(len(pool), p=shares / shares.sum()))]
    u = rng.uniform(size=3)
    lo, hi = np.array([kind.length, kind.width, kind.height]).T
    half = 0.5 * (lo + u * (hi - lo))
    paint, color = draw_paint(rng)
    return Vehicle(kind, half, paint, color)


def vehicle_of_size(rng: np.random.Generator, half) -> Vehicle:
    """A passenger vehicle of a given size (``half`` (3,) metres; a hall's cars keep the sizes
    their layout was drawn with): an SUV from 1.55 m tall, else a hatchback under 4.2 m long,
    else a sedan; the paint from :func:`draw_paint`."""
    half = np.asarray(half, np.float64)
    name = "suv" if 2 * half[2] >= 1.55 else "hatchback" if 2 * half[0] < 4.2 else "sedan"
    paint, color = draw_paint(rng)
    return Vehicle(next(k for k in KINDS if k.name == name), half, paint, color)
