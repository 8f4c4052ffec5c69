"""How the rig's sensor differs from the one a scan was planned with, field by field: what a resume compares.

A scan resumed with another sensor model would mix two sensors in one capture. The differences are told apart by who
can set them back: a [sensor] key of the rig (the operator restores it), or the installed spadscan's preset of the
same name (an update refitted it: only the version that started the scan gives the old one back). On a backend
whose histograms do not depend on the model (a real sensor), a refitted preset stops nothing: the capture keeps the
model it records (`SensorDifference.preset_blocks`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import SensorModelError
from spadscan.protocol.sensor_model import SensorModel
from spadscan.protocol.sensor_presets import sensor_preset

from .backends import SENSOR_BACKENDS, SensorBackend
from .backends.sensor_sim import SimSensorSettings


MODEL_KEYS = SimSensorSettings.model_keys
"""Sensor model fields a [sensor] key sets (sim: power, ambient, cycles); every other field is the preset's. What a
resume compares where the rig's backend is not known (a capture another way made)."""
SCENE_KEYS = {"builtin": "mesh", "mesh": "mesh", "mesh_offset_m": "mesh_offset_m", "albedo": "albedo"}
"""Scene record fields (sim) that change what the sensor sees, and the [sensor] key of each."""
FREE_TEXT = frozenset({"notes"})
"""Sensor model fields that say nothing about what a histogram means, and so are not compared: a preset's reworded
`notes` (where its numbers come from) must not block a resume. Every other field of protocol/sensor_model.py's
SensorModel changes it, and is compared: `name` (which preset), `n_bins`, `bin_width_m` and `zero_bin` (the time
axis: the range a bin stands for), `zones` (where each channel looks, and its gain), `pulse` (the shape a return
takes), `signal_scale`, `background`, `cycles`, `pileup`, `crosstalk`, `jitter_bins` and `max_count` (the counts a
scene gives), `ignore_bins` (the bins a fit must leave out of every frame alike) and `has_reference` (whether frames
carry a reference histogram). A field added later is compared until it is named here."""
@dataclass(frozen=True)
class SensorDifference:
    """How the rig's sensor differs from the one a capture was planned with."""

    keys: list[str]
    """The [sensor] keys that differ, sorted: the operator can set them back."""
    preset: list[str]
    """How the installed spadscan's preset of the same name differs (`preset_changes`): no key can set it back."""
    preset_blocks: bool
    """Whether the preset's difference stops the scan: the sensor renders with the model (sim), the zone or bin
    counts differ, or the rig's backend is not known. Else a real sensor's scan goes on with the model its capture
    records (its histograms do not depend on it)."""
    backend: str = ""
    """The rig's sensor backend now."""


NO_DIFFERENCE = SensorDifference([], [], False)


def sensor_differences(reader: CaptureReader, model_now: SensorModel, rig_now: dict,
                       scene_now: dict) -> SensorDifference:
    """How the rig's sensor now (model_now: its sensor model; rig_now, scene_now: the rig and scene records a new
    capture would get) differs from the one the capture at `reader` was planned with, in what it measures: the
    [sensor] keys that differ (the preset chosen, the keys that set the model, the backend, the sim's scene), and how
    the installed preset of the same name differs (`_attribute`). Records absent on either side (a capture another
    way made) are not compared."""
    then, now = _plain(reader.sensor.to_dict()), _plain(model_now.to_dict())
    rig_then = (reader.manifest.get("rig") or {}).get("sensor") or {}
    rig_now = rig_now.get("sensor") or {}
    backend = SENSOR_BACKENDS.get(rig_now.get("backend"))
    keys, preset = set(), ({}, {})
    if then["name"] != now["name"]:
        keys.add("preset")
    else:
        differ = [name for name in _fields_of(then, now) if name not in FREE_TEXT and then.get(name) != now.get(name)]
        named, preset = _attribute(differ, then, now, rig_then, rig_now, backend)
        keys.update(named)
    if rig_then and rig_now and rig_then.get("backend") != rig_now.get("backend"):
        keys.add("backend")
    scene_then = reader.manifest.get("scene") or {}
    if scene_then and scene_now:
        keys.update(key for name, key in SCENE_KEYS.items() if scene_then.get(name) != scene_now.get(name))
    blocks = backend is None or backend.renders_with_model or _counts_differ(then, now)
    return SensorDifference(sorted(keys), preset_changes(*preset), blocks, rig_now.get("backend") or "")


def _attribute(differ: list[str], then: dict, now: dict, rig_then: dict, rig_now: dict,
               backend: type[SensorBackend] | None) -> tuple[set[str], tuple[dict, dict]]:
    """Which of the model fields in `differ` (same preset name) a changed [sensor] key made, and which the
    installed preset did: (the keys named, (the preset's fields then, now)). Where the capture's rig record holds
    the backend's model keys (`SensorBackend.model_keys`: the sim's power, ambient, cycles; none for a real
    sensor), they are compared key to key (`_by_keys`); a capture that holds none of them is inferred from
    (`_inferred`)."""
    cls = backend or SimSensorSettings  # (a backend not known: the sim's keys, the only ones there are)
    if all(key in rig_then and key in rig_now for key in cls.model_keys.values()):
        return _by_keys(differ, then, now, rig_then, rig_now, cls)
    return _inferred(differ, then, now, rig_now, cls)


def _by_keys(differ: list[str], then: dict, now: dict, rig_then: dict, rig_now: dict,
             cls: type[SensorBackend]) -> tuple[set[str], tuple[dict, dict]]:
    """`_attribute` with the model keys recorded on both sides: a key that differs is named; every difference of
    the preset's own values (the model with the keys undone, `SensorBackend.preset_value`; now: the installed
    preset's) is the preset's, the keys as they were or not."""
    installed = _installed(now["name"])
    named, preset_then, preset_now = set(), {}, {}
    for name in differ:
        key = cls.model_keys.get(name)
        if key is None:
            preset_then[name], preset_now[name] = then.get(name), now.get(name)
            continue
        if rig_then.get(key) != rig_now.get(key):
            named.add(key)
        was = cls.preset_value(name, then.get(name), rig_then)
        is_ = installed[name] if name in installed else cls.preset_value(name, now.get(name), rig_now)
        if was is not None and is_ is not None and not _same(was, is_):
            preset_then[name], preset_now[name] = was, is_
        elif key not in named and name not in preset_then:
            # The keys the same, and the preset's values not to be told apart: the model still differs, so say how.
            preset_then[name], preset_now[name] = then.get(name), now.get(name)
    return named, (preset_then, preset_now)


def _inferred(differ: list[str], then: dict, now: dict, rig_now: dict,
              cls: type[SensorBackend]) -> tuple[set[str], tuple[dict, dict]]:
    """`_attribute` for a capture whose rig record holds no model keys (one started before they were recorded). A
    field no key sets can differ only by the preset. A field a key sets is put down to the preset only when the
    preset is seen to have changed (a field of the first kind differs: an update refitted it) and the value now is
    the installed preset's own (`preset_value`: for power, the signal_scale divided by it); otherwise the key is
    named, as the operator can set it back."""
    if all(name in cls.model_keys for name in differ):
        return {cls.model_keys[name] for name in differ}, ({}, {})
    installed = _installed(now["name"])
    named = {cls.model_keys[name] for name in differ
             if name in cls.model_keys and not (name in installed and
                                               _same(cls.preset_value(name, now.get(name), rig_now), installed[name]))}
    preset = [name for name in differ if cls.model_keys.get(name) not in named]
    return named, ({name: then.get(name) for name in preset}, {name: now.get(name) for name in preset})


def _installed(name: str) -> dict:
    """The installed spadscan's preset `name` as a plain record; {} when it has none of that name."""
    try:
        return _plain(sensor_preset(name).to_dict())
    except SensorModelError:
        return {}


def _same(a, b) -> bool:
    """Two values of a model field alike, numbers to 1e-9 (a value the keys were undone from is divided)."""
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(a, b, rel_tol=1e-9)
    return a == b


def _counts_differ(then: dict, now: dict) -> bool:
    """Whether two sensor model records differ in their zone or bin counts (what a real sensor's driver checks a
    model against: the histograms of one capture must have one shape)."""
    zones = lambda record: len(record.get("zones") or [])  # noqa: E731
    return then.get("n_bins") != now.get("n_bins") or zones(then) != zones(now)


def preset_changes(then: dict, now: dict) -> list[str]:
    """Each value that differs between two sensor model records (plain JSON), as 'field then -> now' (nested ones
    by their path: pulse.sigma_bins, zones[4].gain), or 'field changed' where a value is too long to show (a pulse
    table); in the records' field order."""
    return _differences(then, now, "")


SHOWN_MAX = 24
"""Characters of a value a block shows (longer ones: 'changed')."""


def _differences(then, now, path: str) -> list[str]:
    """`preset_changes` of two values at `path`: objects, and lists of objects of one length, are walked into."""
    if then == now:
        return []
    if isinstance(then, dict) and isinstance(now, dict):
        keys = list(then) + [key for key in now if key not in then]
        return [said for key in keys
                for said in _differences(then.get(key), now.get(key), f"{path}.{key}" if path else key)]
    if _records(then) and _records(now):
        if len(then) != len(now):
            return [f"{path} {len(then)} -> {len(now)} entries"]
        return [said for i, (a, b) in enumerate(zip(then, now)) for said in _differences(a, b, f"{path}[{i}]")]
    shown = (_shown(then), _shown(now))
    return [f"{path} changed" if max(map(len, shown)) > SHOWN_MAX else f"{path} {shown[0]} -> {shown[1]}"]


def _records(value) -> bool:
    """A non-empty list of JSON objects (a model's zones)."""
    return isinstance(value, list) and bool(value) and all(isinstance(item, dict) for item in value)


def _shown(value) -> str:
    """A plain value as a block says it: numbers short (12.4, 0.0136091), lists in brackets, absent as (none)."""
    if value is None:
        return "(none)"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return "[" + ", ".join(map(_shown, value)) + "]"
    return json.dumps(value)


def _fields_of(then: dict, now: dict) -> list[str]:
    """The fields of two model records, in their order (then's first)."""
    return list(then) + [name for name in now if name not in then]


def _plain(record: dict) -> dict:
    """A record as JSON has it (tuples as lists), so that a stored one and a fresh one compare equal."""
    return json.loads(json.dumps(record))
