"""Settings removed from the configuration, each with the one value its code path now
always takes. A config.yaml (`jaxmripp.config`) or an export header (`jaxmripp.runtime`)
written before a removal still holds them: it is read where it holds that value and
refused otherwise, so no older run or export silently means something else.
"""

from __future__ import annotations

from typing import Any

# "section.key" -> the value built in, as YAML and JSON write it
BUILT_IN: dict[str, Any] = {
    "train.radio_ranges": [],
    "radio.map_reach": "radio",
    "radio.sector_split": "angle",
    "radio.sector_count": 0,
    "train.sectors": False,
    "reward.team_share": 0.0,
    "policy.claims": False,
    "safety.takeoff_scan": False,
    "safety.intents": True,
    "safety.priority": "id",
    "gp.peer_rounds": 255,  # uncapped: N - 1 for every team of at most 256 robots
    "policy.view_prior": 0.0,
    "sensor.gain_tops": "mapped",  # the view gain reads the map's tops
}


def is_built_in(key: str, value: Any) -> bool:
    """Whether `value` of the removed setting `key` is the one its code now builds in (a
    list as any sequence; a bool only as a bool, and no number as one)."""
    built_in = BUILT_IN[key]
    if isinstance(built_in, list):
        return isinstance(value, (list, tuple)) and list(value) == built_in
    if isinstance(built_in, bool) or isinstance(value, bool):
        return value is built_in
    return value == built_in
