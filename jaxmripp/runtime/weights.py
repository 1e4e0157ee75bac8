"""The exported policy format: `policy.npz` (weights) + `policy.json` (header).

Written by `jaxmripp.export` (the JAX side) through `save`, read onboard through `load`.
Both live here so that the format has one definition, and this module imports nothing but
NumPy and the standard library.

policy.json
    format            "jaxmripp-policy"
    format_version    FORMAT_VERSION; a reader refuses any other version
    layout            {"features": [...], "robot_state": [...]}: the column order of the
                      policy's inputs, which must equal this runtime's
                      `features(ahead, belief)` (FEATURES, with the belief input when
                      config.belief.features, then the lookahead input when
                      config.ahead.branches > 0) / ROBOT_STATE
    config            the values the onboard planner needs (see `RuntimeSpec.from_header`):
                      world.size, sensor.*, candidates.*, robots.*, radio.*, safety.* (escape
                      may be absent: off),
                      gp.*, reward.utility_norm, episode.max_steps, ahead.* (the
                      lookahead input of `jaxmripp.spec.layout`: branches, discount,
                      facade_weight, rated (absent: false); absent: none), belief.* (the target belief of
                      `jaxmripp.spec.belief`: features, strength and the trained world's
                      prior rate m; written with the belief input only); infinities are the
                      string "inf". The runtime flies safety.flight "known_free" only and
                      needs radio.share_maps (whether robots exchange maps); settings since
                      removed (`spec.REMOVED`) may appear only at the value built in.
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
from jaxmripp.runtime.spec import GPSpec, RuntimeSpec, header_field  # noqa: F401
from jaxmripp.spec import belief
from jaxmripp.spec.layout import ROBOT_STATE, features

FORMAT = "jaxmripp-policy"
FORMAT_VERSION = 1
WEIGHTS_FILE = "policy.npz"
HEADER_FILE = "policy.json"


def config_header(cfg) -> dict[str, Any]:
    """The header's `config` block from a `jaxmripp.config.Config` (read by attribute, so
    this module needs no import of it)."""
    head = {
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
                  "facade_weight": cfg.policy.ahead_facade_weight,
                  "rated": cfg.policy.ahead_rated},
    }
    if cfg.policy.belief_features:  # absent: no belief input (as exports before it)
        world = cfg.world
        head["belief"] = {"features": True, "strength": cfg.policy.belief_strength,
                          "prior": belief.prior_rate(
                              world.size, world.n_buildings, world.footprint,
                              world.footprint_min, world.height_range,
                              (world.target_min, world.target_capacity),
                              world.target_placement)}
    return jsonable(head)


def header(cfg, policy_config: Mapping[str, Any], source: Mapping | None = None) -> dict:
    """A complete policy.json header less its `weights` block (added by `save`)."""
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "layout": {"features": list(features(cfg.policy.ahead_branches > 0,
                                             cfg.policy.belief_features)),
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
    layout = header_field(header, "layout", dict)
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
    block = header_field(header, "weights", dict)
    npz_path = json_path.parent / str(header_field(block, "file", str, "weights."))
    expected = header_field(block, "sha256", str, "weights.")
    weights = _read_npz(npz_path)
    if weights_sha256(weights) != expected:
        raise CorruptWeightsError(f"{npz_path}: weights do not match the sha256 recorded in "
                                  f"{json_path.name}")
    config = header_field(header, "policy", dict)
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
