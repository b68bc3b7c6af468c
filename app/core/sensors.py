"""Which kind of scanner recorded a survey: the fact that decides which learned model may run on it.

The two kinds sample a street differently, so a model trained on one is off-domain on the other:

- `rotating`: a spinning multi-beam scanner (Velodyne HDL-64E / VLP-32, Ouster, Hesai ...): every
  revolution (0.05-0.2 s) re-measures the whole surround from the vehicle's new position, so a
  static surface is hit again and again as the vehicle passes, by a few rings at grazing angles.
- `profile`: a 2D line scanner on a mobile-mapping van (RIEGL VQ-250 / VUX, Z+F profiler ...):
  a fixed scan plane sweeps the street once as the vehicle drives, 50-500 lines per second, a
  dense profile each.
- `unknown`: not told by the reader and not detectable from the data; the operator declares it.
"""

from __future__ import annotations

from enum import StrEnum


class SensorKind(StrEnum):
    ROTATING = "rotating"
    PROFILE = "profile"
    UNKNOWN = "unknown"


# scanner model names the readers and the simulator use -> their kind
SCANNER_KINDS: dict[str, SensorKind] = {
    "hdl64": SensorKind.ROTATING,
    "profile": SensorKind.PROFILE,
}

# the kinds a model can be trained for and a survey declared as
KNOWN_KINDS: tuple[SensorKind, ...] = (SensorKind.ROTATING, SensorKind.PROFILE)


def kind_of_scanner(scanner: str | None) -> SensorKind:
    """The kind of a named scanner model; unknown for None or an unnamed model."""
    return SCANNER_KINDS.get(scanner or "", SensorKind.UNKNOWN)


def parse_sensor_kind(value: str, *, allow_unknown: bool = True) -> SensorKind:
    """`value` as a SensorKind; ValueError naming the allowed values otherwise."""
    allowed = [k.value for k in (SensorKind if allow_unknown else KNOWN_KINDS)]
    text = str(value).strip().lower()
    if text not in allowed:
        raise ValueError(f"unknown sensor kind {value!r}; use one of: {', '.join(allowed)}")
    return SensorKind(text)
