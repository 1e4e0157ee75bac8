"""The presets shipped inside the package (jaxmripp/configs/*.yaml) and where a name or a
path given on the command line points.

`--config recipe_quick` is the packaged recipe_quick.yaml from any working directory; a path
to a YAML file works as well (the repository's `configs/` links to the packaged folder, so
`configs/recipe_quick.yaml` from the repository root is the same file). Each preset starts
with a one-line summary comment, which `--help` lists. The names say what a preset is:
`recipe_*` trains a policy, `world_*` sets up a world, `protocol_*` evaluates.
"""

from __future__ import annotations

from pathlib import Path

from jaxmripp.config.errors import ConfigError

PRESETS = Path(__file__).resolve().parents[1] / "configs"
DEFAULT = "recipe_quick"  # what `make train` trains: --config's default
# The source checkout the package was installed from (an editable install); holds
# benchmarks/ and pretrained/ where it is one.
CHECKOUT = Path(__file__).resolve().parents[2]


def names() -> list[str]:
    """Every packaged preset's name, sorted."""
    return sorted(path.stem for path in PRESETS.glob("*.yaml"))


def is_name(source: str | Path) -> bool:
    """Whether `source` reads as a preset name rather than a path: no folder part and no
    YAML suffix."""
    text = str(source)
    return "/" not in text and "\\" not in text and not text.endswith((".yaml", ".yml"))


def resolve(source: str | Path) -> Path:
    """The file `source` names: an existing file as it is, a bare name as the packaged
    preset of that name (ConfigError listing the names where there is none), anything else
    as the path it is (whose absence `config.load` reports)."""
    path = Path(source)
    if path.is_file() or not is_name(source):
        return path
    preset = PRESETS / f"{source}.yaml"
    if not preset.is_file():
        raise ConfigError(f"{source}: no such preset; allowed: a config file or a preset "
                          f"name ({', '.join(names()) or 'none found'})")
    return preset


def summary(name: str) -> str:
    """The first line of a preset's header comment ('' where it has none)."""
    lines = (PRESETS / f"{name}.yaml").read_text().splitlines()
    return lines[0].lstrip("#").strip() if lines and lines[0].startswith("#") else ""


def listing() -> str:
    """Every preset with its summary, one a line, for `--help`."""
    width = max(map(len, names()), default=0)
    return "\n".join(f"  {name:<{width}}  {summary(name)}" for name in names())


def in_checkout(path: str | Path) -> Path:
    """A relative path missing from the working directory but present in the source
    checkout (e.g. `pretrained/default` as a `train.init_from`) as the checkout's; otherwise
    the path as given."""
    path = Path(path)
    if path.is_absolute() or path.exists() or not (CHECKOUT / path).exists():
        return path
    return CHECKOUT / path
