"""The exported policy format: `policy.npz` (weights) + `policy.json` (header).

Written by `jaxmripp.export` (the JAX side) through `save`, read onboard through `load`.
Both live here so that the format has one definition, and this module imports nothing but
NumPy and the standard library.

policy.json
    format            "jaxmripp-policy"
    format_version    FORMAT_VERSION; a reader refuses any other version
    layout            {"features": [...], "robot_state": [...]}: the column order of the
                      policy's inputs, which must equal this runtime's
                      `features(ahead)` (FEATURES, with the lookahead input when
                      config.ahead.branches > 0) / ROBOT_STATE
    config            the values the onboard planner needs (see `RuntimeSpec.from_header`):
                      world.size, sensor.*, candidates.*, robots.*, radio.*, safety.* (escape
                      may be absent: off),
                      gp.*, reward.utility_norm, episode.max_steps, ahead.* (the
                      lookahead input of `jaxmripp.spec.layout`: branches, discount,
                      facade_weight; absent: none); infinities are the
                      string "inf". The runtime flies safety.flight "known_free" only
                      and needs radio.share_maps (whether robots exchange maps).
    policy            jaxmripp.learn.policy.runtime_config (width, heads, layers, ff_mult,
                      central_critic)
    weights           {"file": "policy.npz", "sha256": ..., "arrays": n, "parameters": n}
    source            free-form provenance (run directory, checkpoint step)

policy.npz: one float32 array per "/"-joined parameter path (jaxmripp.learn.policy.flatten_params).
The sha256 is over the arrays, not the zip bytes (zip entries carry timestamps): for each
name in sorted order, the name, dtype, shape and little-endian bytes (see `weights_sha256`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from jaxmripp.runtime.errors import CorruptWeightsError, WeightsFormatError
from jaxmripp.runtime.policy import NumpyPolicy
from jaxmripp.runtime.view import GainModel
from jaxmripp.spec.flight import PRIORITIES
from jaxmripp.spec.layout import ROBOT_STATE, features
from jaxmripp.spec.view import FACADE_TOPS

FORMAT = "jaxmripp-policy"
FORMAT_VERSION = 1
WEIGHTS_FILE = "policy.npz"
HEADER_FILE = "policy.json"

# ---------------------------------------------------------------------------------------
# What the planner needs from a config


@dataclasses.dataclass(frozen=True)
class GPSpec:
    capacity: int
    length_scale: float
    heading_scale: float
    variance: float
    noise: float
    catchup_rounds: int
    eval_grid: int


_GP_FIELDS = {"capacity": int, "length_scale": float, "heading_scale": float,
              "variance": float, "noise": float, "catchup_rounds": int, "eval_grid": int}


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
    # Safe flight (jaxmripp.spec.flight): the obstacle rule (always "known_free" here),
    # whether the first sense is a take-off scan, whether robots exchange intents and hold,
    # who goes first ("id" or "budget") and whether robots too close may part (escape).
    flight: str = "known_free"
    takeoff_scan: bool = True
    intents: bool = True
    priority: str = "id"
    escape: bool = False
    # The lookahead input (jaxmripp.spec.layout): candidates followed (0: no such input),
    # the later flight's weight and the facade weight of its view value.
    ahead_branches: int = 0
    ahead_discount: float = 2.0
    ahead_facade_weight: float = 2.0
    # The view gain's model of the sensor and the world (sensor.gain_occlusion and
    # sensor.gain_facade; jaxmripp.spec.view).
    gain_occlusion: bool = True
    gain_facade: str = "nearby"

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
        return features(self.ahead_branches > 0)

    @classmethod
    def from_header(cls, header: Mapping[str, Any]) -> "RuntimeSpec":
        config = _field(header, "config", dict)
        section = lambda name: _field(config, name, dict, "config.")  # noqa: E731

        def get(name, key, kind):
            value = _field(section(name), key, object, f"config.{name}.")
            return _convert(value, kind, f"config.{name}.{key}")

        gp = section("gp")
        if "safety" not in config:
            raise WeightsFormatError("export header: missing field config.safety (exported "
                                     "before the safe-flight rules; re-export the policy)")
        flight = get("safety", "flight", str)
        if flight != "known_free":
            raise WeightsFormatError(
                f"export header: config.safety.flight is {flight!r}; the onboard runtime "
                "flies known_free only (export a policy trained with safety.flight="
                "known_free)")
        if "share_maps" not in section("radio"):
            raise WeightsFormatError("export header: missing field config.radio.share_maps "
                                     "(exported before map sharing, protocol 3; re-export "
                                     "the policy)")
        priority = get("safety", "priority", str)
        if priority not in PRIORITIES:
            raise WeightsFormatError(f"export header: config.safety.priority {priority!r} is "
                                     f"not one of {', '.join(PRIORITIES)}")
        gain = {}  # exports from before these settings lack them: the defaults apply
        if "gain_occlusion" in section("sensor"):
            gain["gain_occlusion"] = get("sensor", "gain_occlusion", bool)
        if "gain_facade" in section("sensor"):
            gain["gain_facade"] = get("sensor", "gain_facade", str)
            if gain["gain_facade"] not in FACADE_TOPS:
                raise WeightsFormatError(f"export header: config.sensor.gain_facade "
                                         f"{gain['gain_facade']!r} is not one of "
                                         f"{', '.join(FACADE_TOPS)}")
        ahead = {}
        if "ahead" in config:  # exports without the lookahead input may lack the section
            ahead = dict(ahead_branches=get("ahead", "branches", int),
                         ahead_discount=get("ahead", "discount", float),
                         ahead_facade_weight=get("ahead", "facade_weight", float))
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
            radio_range=get("radio", "range", float),
            relay=get("radio", "relay", bool),
            share_maps=get("radio", "share_maps", bool),
            collision_distance=get("radio", "collision_distance", float),
            gp=GPSpec(**{name: _convert(_field(gp, name, object, "config.gp."), kind,
                                        f"config.gp.{name}")
                         for name, kind in _GP_FIELDS.items()}),
            utility_norm=get("reward", "utility_norm", float),
            max_steps=get("episode", "max_steps", int),
            flight=flight,
            takeoff_scan=get("safety", "takeoff_scan", bool),
            intents=get("safety", "intents", bool),
            priority=priority,
            # Optional in the header (absent: off).
            escape=(get("safety", "escape", bool) if "escape" in section("safety")
                    else False),
            **gain, **ahead,
        )


def _field(mapping, key, kind, prefix=""):
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


def config_header(cfg) -> dict[str, Any]:
    """The header's `config` block from a `jaxmripp.config.Config` (read by attribute, so
    this module needs no import of it)."""
    return jsonable({
        "world": {"size": cfg.world.size},
        "sensor": dataclasses.asdict(cfg.sensor),
        "candidates": dataclasses.asdict(cfg.candidates),
        "robots": {"count": cfg.robots.count, "turn_cost": cfg.robots.turn_cost,
                   "budget": list(cfg.robots.budget), "start": list(cfg.robots.start),
                   "start_heading": cfg.robots.start_heading,
                   "pad_spacing": cfg.robots.pad_spacing},
        "radio": dataclasses.asdict(cfg.radio),
        "safety": dataclasses.asdict(cfg.safety),
        "gp": dataclasses.asdict(cfg.gp),
        "reward": {"utility_norm": cfg.reward.utility_norm},
        "episode": {"max_steps": cfg.episode.max_steps},
        "ahead": {"branches": cfg.policy.ahead_branches,
                  "discount": cfg.policy.ahead_discount,
                  "facade_weight": cfg.policy.ahead_facade_weight},
    })


def header(cfg, policy_config: Mapping[str, Any], source: Mapping | None = None) -> dict:
    """A complete policy.json header less its `weights` block (added by `save`)."""
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "layout": {"features": list(features(cfg.policy.ahead_branches > 0)),
                   "robot_state": list(ROBOT_STATE)},
        "config": config_header(cfg),
        "policy": dict(policy_config),
        "source": jsonable(dict(source or {})),
    }


def jsonable(value: Any) -> Any:
    """Plain data with infinities as the strings "inf" / "-inf" (strict JSON has none)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        if math.isnan(value):
            raise ValueError("NaN cannot be exported")
        return value
    return value


# ---------------------------------------------------------------------------------------
# Writing and reading


def weights_sha256(weights: Mapping[str, np.ndarray]) -> str:
    """Hash of the arrays themselves (name, dtype, shape, bytes), independent of the zip."""
    digest = hashlib.sha256()
    for name in sorted(weights):
        array = np.ascontiguousarray(weights[name])
        if array.dtype.byteorder == ">":
            array = array.astype(array.dtype.newbyteorder("<"))
        digest.update(name.encode() + b"\0" + array.dtype.str.encode() + b"\0")
        digest.update(repr(tuple(array.shape)).encode() + b"\0" + array.tobytes())
    return digest.hexdigest()


def save(out_dir: str | Path, weights: Mapping[str, np.ndarray], header: Mapping[str, Any]
         ) -> tuple[Path, Path]:
    """Writes policy.npz and policy.json into out_dir (atomically, file by file)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    weights = {name: np.asarray(value, np.float32) for name, value in weights.items()}
    header = dict(header)
    header["format"], header["format_version"] = FORMAT, FORMAT_VERSION
    header["weights"] = {
        "file": WEIGHTS_FILE,
        "sha256": weights_sha256(weights),
        "arrays": len(weights),
        "parameters": int(sum(v.size for v in weights.values())),
    }
    npz_path, json_path = out_dir / WEIGHTS_FILE, out_dir / HEADER_FILE
    tmp = npz_path.with_name(npz_path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **weights)
    os.replace(tmp, npz_path)
    tmp = json_path.with_name(json_path.name + ".tmp")
    tmp.write_text(json.dumps(jsonable(header), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, json_path)
    return npz_path, json_path


@dataclasses.dataclass(frozen=True)
class ExportedPolicy:
    """A loaded export: header, spec, weights and the ready NumPy policy."""

    header: dict
    spec: RuntimeSpec
    weights: dict
    policy: NumpyPolicy
    path: Path


def read_header(path: str | Path) -> dict:
    """Reads and checks policy.json (path: the file or its directory)."""
    path = Path(path)
    if path.is_dir():
        path = path / HEADER_FILE
    try:
        text = path.read_text()
    except OSError as err:
        raise CorruptWeightsError(f"{path}: cannot read ({err.strerror or err})") from None
    try:
        header = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CorruptWeightsError(f"{path}: truncated or not JSON ({err})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise WeightsFormatError(f"{path}: not a {FORMAT} header")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise WeightsFormatError(f"{path}: format version {version!r}; this runtime reads "
                                 f"version {FORMAT_VERSION} (re-export with a matching jaxmripp)")
    layout = _field(header, "layout", dict)
    expected_features = RuntimeSpec.from_header(header).features
    for key, expected in (("features", expected_features), ("robot_state", ROBOT_STATE)):
        if tuple(layout.get(key, ())) != expected:
            raise WeightsFormatError(f"{path}: layout.{key} differs from this runtime's "
                                     f"{key} layout")
    return header


def load(path: str | Path) -> ExportedPolicy:
    """Loads an export directory (or its policy.json) and verifies the weights' hash."""
    path = Path(path)
    json_path = path / HEADER_FILE if path.is_dir() else path
    header = read_header(json_path)
    spec = RuntimeSpec.from_header(header)
    block = _field(header, "weights", dict)
    npz_path = json_path.parent / str(_field(block, "file", str, "weights."))
    expected = _field(block, "sha256", str, "weights.")
    weights = _read_npz(npz_path)
    if weights_sha256(weights) != expected:
        raise CorruptWeightsError(f"{npz_path}: weights do not match the sha256 recorded in "
                                  f"{json_path.name}")
    config = _field(header, "policy", dict)
    try:
        policy = NumpyPolicy(weights, config)
    except (KeyError, ValueError, TypeError) as err:
        message = err.args[0] if err.args else type(err).__name__
        raise WeightsFormatError(f"{npz_path}: weights do not fit the header's policy "
                                 f"({message})") from None
    if policy.n_features != len(spec.features):
        raise WeightsFormatError(f"{npz_path}: the policy reads {policy.n_features} features; "
                                 f"this runtime builds {len(spec.features)}")
    return ExportedPolicy(header, spec, weights, policy, json_path.parent)


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            weights = {name: np.asarray(data[name]) for name in data.files}
    except FileNotFoundError:
        raise CorruptWeightsError(f"{path}: no such weights file") from None
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as err:
        raise CorruptWeightsError(f"{path}: truncated or corrupt weights file "
                                  f"({type(err).__name__}: {err})") from None
    if not weights:
        raise CorruptWeightsError(f"{path}: the weights file holds no arrays")
    return weights
