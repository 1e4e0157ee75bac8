"""What the onboard planner needs from an exported policy's config: `RuntimeSpec`, read
from the `config` block of a policy.json header (`jaxmripp.runtime.weights`) with one clear
error per missing or malformed field.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Mapping

from jaxmripp.runtime.errors import WeightsFormatError
from jaxmripp.runtime.view import GainModel
from jaxmripp.spec import removed
from jaxmripp.spec.layout import features
from jaxmripp.spec.view import FACADE_TOPS


@dataclasses.dataclass(frozen=True)
class GPSpec:
    capacity: int
    length_scale: float
    heading_scale: float
    variance: float
    noise: float
    catchup_rounds: int
    eval_grid: int


# The removed settings (jaxmripp.spec.removed) of the sections the runtime flies by, as
# (section, key): a header written before their removal holds them, and is refused at any
# other value than the one built in.
REMOVED = {tuple(key.split(".")): value for key, value in removed.BUILT_IN.items()
           if key.split(".")[0] in ("radio", "safety", "gp")}

_GP_FIELDS = typing.get_type_hints(GPSpec)  # {field: int or float}


@dataclasses.dataclass(frozen=True)
class RuntimeSpec:
    """The config values the onboard planner uses, read from a header's `config`."""

    size: int  # G, voxels per side of the unit cube
    positions: int  # K candidate positions; L = 4 K
    shell: tuple[float, float]
    oversample: int
    turn_cost: float
    team_size: int  # robots.count the policy was trained with (a default only)
    start: tuple[float, float, float]
    start_heading: int
    fov_deg: float  # the camera's, for the view-gain features (jaxmripp.spec.view)
    sensor_range: float
    radio_range: float
    relay: bool
    share_maps: bool  # robots in range exchange map deltas (jaxmripp.spec.sharing)
    collision_distance: float
    gp: GPSpec
    utility_norm: float
    max_steps: int
    # Safe flight (jaxmripp.spec.flight): the obstacle rule (always "known_free" here) and
    # whether robots too close may part (escape).
    flight: str = "known_free"
    escape: bool = False
    # The lookahead input (jaxmripp.spec.layout): candidates followed (0: no such input),
    # the later flight's weight, the facade weight of its view value and whether the facade
    # is weighed by the target belief.
    ahead_branches: int = 0
    ahead_discount: float = 2.0
    ahead_facade_weight: float = 2.0
    ahead_rated: bool = False
    # The view gain's model of the sensor and the world (sensor.gain_occlusion and
    # sensor.gain_facade; jaxmripp.spec.view).
    gain_occlusion: bool = True
    gain_facade: str = "nearby"
    # The target belief (jaxmripp.spec.belief): whether the policy reads its columns, the
    # prior strength k (policy.belief_strength) and the prior rate m of the trained world.
    belief_features: bool = False
    belief_strength: float = 3.0
    belief_prior: float = 0.0

    @property
    def gain(self) -> GainModel:
        """What the view-gain features assume of the sensor (`jaxmripp.runtime.view`)."""
        return GainModel(self.fov_deg, self.sensor_range, self.gain_occlusion,
                         self.gain_facade)

    @property
    def n_candidates(self) -> int:
        return 4 * self.positions

    @property
    def features(self) -> tuple[str, ...]:
        """The policy's input columns (`jaxmripp.spec.layout.features`)."""
        return features(self.ahead_branches > 0, self.belief_features)

    @classmethod
    def from_header(cls, header: Mapping[str, Any]) -> "RuntimeSpec":
        config = header_field(header, "config", dict)
        section = lambda name: header_field(config, name, dict, "config.")  # noqa: E731

        def get(name, key, kind, default=None):
            """config.name.key as `kind`; a field exported before it existed (absent) is
            `default` where one is given."""
            if default is not None and key not in section(name):
                return default
            value = header_field(section(name), key, object, f"config.{name}.")
            return _convert(value, kind, f"config.{name}.{key}")

        def choice(name, key, allowed, default=None):
            value = get(name, key, str, default)
            if value not in allowed:
                raise WeightsFormatError(f"export header: config.{name}.{key} {value!r} is "
                                         f"not one of {', '.join(allowed)}")
            return value

        if "safety" not in config:
            raise WeightsFormatError("export header: missing field config.safety (exported "
                                     "before the safe-flight rules; re-export the policy)")
        flight = get("safety", "flight", str)
        if flight != "known_free":
            raise WeightsFormatError(
                f"export header: config.safety.flight is {flight!r}; the onboard runtime "
                "flies known_free only (export a policy trained with safety.flight="
                "known_free)")
        for (name, key), built_in in REMOVED.items():
            value = section(name).get(key, built_in)
            if not removed.is_built_in(f"{name}.{key}", value):
                raise WeightsFormatError(
                    f"export header: config.{name}.{key} is {value!r}, a removed setting; "
                    f"the runtime has only {built_in!r} (export a policy trained without it)")
        if "share_maps" not in section("radio"):
            raise WeightsFormatError("export header: missing field config.radio.share_maps "
                                     "(exported before map sharing, protocol 3; re-export "
                                     "the policy)")
        ahead: dict[str, Any] = {}  # the optional sections' fields
        if "ahead" in config:  # exports without the lookahead input may lack the section
            ahead = dict(ahead_branches=get("ahead", "branches", int),
                         ahead_discount=get("ahead", "discount", float),
                         ahead_facade_weight=get("ahead", "facade_weight", float),
                         ahead_rated=get("ahead", "rated", bool, False))
        if "belief" in config:  # exports from before the belief input lack the section
            ahead.update(belief_features=get("belief", "features", bool),
                         belief_strength=get("belief", "strength", float),
                         belief_prior=get("belief", "prior", float))
            for key in ("strength", "prior") if ahead["belief_features"] else ():
                if not 0 < ahead[f"belief_{key}"] < math.inf:
                    raise WeightsFormatError(f"export header: config.belief.{key} is "
                                             f"{ahead[f'belief_{key}']}; allowed: a finite "
                                             "number > 0")
        return cls(
            size=get("world", "size", int),
            positions=get("candidates", "positions", int),
            shell=tuple(get("candidates", "shell", (float, 2))),
            oversample=get("candidates", "oversample", int),
            turn_cost=get("robots", "turn_cost", float),
            team_size=get("robots", "count", int),
            start=tuple(get("robots", "start", (float, 3))),
            start_heading=get("robots", "start_heading", int),
            fov_deg=get("sensor", "fov_deg", float),
            sensor_range=get("sensor", "range", float),
            gain_occlusion=get("sensor", "gain_occlusion", bool, default=True),
            gain_facade=choice("sensor", "gain_facade", FACADE_TOPS, default="nearby"),
            radio_range=get("radio", "range", float),
            relay=get("radio", "relay", bool),
            share_maps=get("radio", "share_maps", bool),
            collision_distance=get("radio", "collision_distance", float),
            gp=GPSpec(**{name: get("gp", name, kind) for name, kind in _GP_FIELDS.items()}),
            utility_norm=get("reward", "utility_norm", float),
            max_steps=get("episode", "max_steps", int),
            flight=flight,
            escape=get("safety", "escape", bool, default=False),
            **ahead,
        )


def header_field(mapping, key, kind, prefix=""):
    """mapping[key], which must exist and be a `kind` (object: anything)."""
    if not isinstance(mapping, Mapping) or key not in mapping:
        raise WeightsFormatError(f"export header: missing field {prefix}{key}")
    value = mapping[key]
    if kind is not object and not isinstance(value, kind):
        raise WeightsFormatError(f"export header: {prefix}{key} is not a {kind.__name__}")
    return value


def _convert(value, kind, name):
    if isinstance(kind, tuple):
        item, count = kind
        if not isinstance(value, list) or len(value) != count:
            raise WeightsFormatError(f"export header: {name} is not a list of {count}")
        return [_convert(v, item, name) for v in value]
    if kind is bool:
        if not isinstance(value, bool):
            raise WeightsFormatError(f"export header: {name} is not true/false")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise WeightsFormatError(f"export header: {name} is not an integer")
        return value
    if kind is str:
        if not isinstance(value, str):
            raise WeightsFormatError(f"export header: {name} is not a string")
        return value
    if isinstance(value, str) and value in ("inf", "-inf"):
        return float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        raise WeightsFormatError(f"export header: {name} is not a number")
    return float(value)
