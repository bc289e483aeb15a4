"""The one command line of every entry point: YAML defaults + the command line, checked, one-line errors.

A setting is given as `key=value`, `--key value` or `--key=value` (in `--key`, dashes read as underscores:
`--max-model-gb 8` is `max_model_gb=8`; a `--flag` with no value is `true`); dotted keys reach nested sections
(`lr.vision=0`). Unknown keys, and values of the wrong shape for their defaults, are one-line errors; a list is
`[a,b]` or `a,b`. `-h` / `--help` prints the entry point's docstring and its
documented defaults. Entry points call `cli_main(fn, __doc__)`: a ConfigError or ValueError becomes
`error: <message>` on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import os
import sys
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterable

from omegaconf import DictConfig, ListConfig, OmegaConf

# Every YAML default ships inside the package (the repository's top-level configs/ links here): entry points and
# backends find them through importlib.resources, from a checkout or an installed wheel alike.
CONFIG_DIR = Path(str(resources.files("labrobfail_vlm") / "configs"))


class ConfigError(ValueError):
    """A bad configuration value or input; the message names the field or file."""


class HelpRequested(Exception):
    """-h / --help: the documented defaults, for cli_main to print after the entry point's docstring."""


def dotlist(argv: list[str]) -> list[str]:
    """`key=value`, `--key value`, `--key=value` and `--flag` -> OmegaConf's `key=value` dotlist."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a.startswith("--") and len(a) > 2:
            key, eq, val = a[2:].partition("=")
            key = key.replace("-", "_")
            if not eq:
                nxt = argv[i + 1] if i + 1 < len(argv) else None
                if nxt is not None and not nxt.startswith("--"):
                    val, i = nxt, i + 1
                else:
                    val = "true"
            out.append(f"{key}={val}")
        elif "=" in a and not a.startswith("-"):
            out.append(a)
        else:
            raise ConfigError(f"argument {a!r}: expected key=value, --key value or --key=value (see --help)")
        i += 1
    return out


def _defaults(defaults: str | Path) -> tuple[DictConfig, str]:
    """(the defaults, their YAML text): a file under configs/, an absolute path, or YAML text itself."""
    text = str(defaults)
    if "\n" in text:  # a script's own small defaults, written inline
        return OmegaConf.create(text), text
    path = CONFIG_DIR / defaults if not Path(defaults).is_absolute() else Path(defaults)
    return OmegaConf.load(path), path.read_text()


def is_int(value: object, low: int) -> bool:
    """An integer (YAML's true is not 1) of at least `low`."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def is_number(value: object) -> bool:
    """An int or a float (YAML's true is not 1)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def require_ints(cfg: Any, keys: Iterable[str], low: int = 1, section: str = "") -> None:
    """A one-line ConfigError naming the first of `keys` in `cfg` (the `section` of a larger config, e.g.
    "prefix.") that is not an integer >= `low`."""
    for key in keys:
        if not is_int(cfg[key], low):
            raise ConfigError(f"{section}{key}: expected an integer >= {low}, got {cfg[key]!r}")


def first_difference(a: Any, b: Any, at: str = "") -> str | None:
    """The dotted key where two JSON values first differ, or None."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                return f"{at}{k}"
            if (d := first_difference(a[k], b[k], f"{at}{k}.")) is not None:
                return d
        return None
    return None if a == b else at.rstrip(".") or "(the whole config)"


def settings_record(cfg: Any, free: Iterable[str]) -> dict[str, Any]:
    """What a checkpoint records of the settings that decide its weights: the resolved config less its `free`
    top-level keys (dropped before resolving, so they never have to resolve), as its JSON file reads back (tuples as
    lists)."""
    import copy
    import json

    conf = copy.deepcopy(cfg)
    OmegaConf.set_struct(conf, False)  # a copy: the run's own config stays closed to new keys
    for k in free:
        conf.pop(k, None)
    return json.loads(json.dumps(OmegaConf.to_container(conf, resolve=True)))


def refuse_other_settings(
    recorded: dict[str, Any],
    now: dict[str, Any],
    free: Iterable[str],
    where: Any,
    record: str,
    fresh: str,
    program: str,
) -> None:
    """A run resuming `where` under other settings than it `recorded` (in file `record`) is a one-line ConfigError
    naming the first key that differs and both values, or a key only one side has; keys freed since the record was
    made are not compared. `fresh`: the setting that names a new folder to start afresh in; `program`: the console
    script that records them."""
    import json

    freed = set(free)  # once: `free` may be a generator, and the set serves every key
    recorded = {k: v for k, v in recorded.items() if k not in freed}
    key = first_difference(recorded, now)
    if key is None:
        return
    was, this = _at(recorded, key), _at(now, key)
    advice = f"start afresh in a new {fresh} (nothing was changed)"
    if was is _MISSING or this is _MISSING:
        which = "without this setting" if was is _MISSING else f"with a setting this {program} lacks"
        raise ConfigError(
            f"{key}: {where} was trained by a {program} {which}; resume it with the code that made it, or {advice}"
        )

    def short(v: Any) -> str:
        text = json.dumps(v)
        return text if len(text) <= 80 else text[:77] + "..."

    raise ConfigError(
        f"{key}: {where} was trained with {short(was)}, this run has {short(this)}; rerun with its settings "
        f"({record}) or {advice}"
    )


_MISSING = object()


def _at(d: Any, key: str) -> Any:
    """The value at a dotted key of a nested dict (first_difference's names), or _MISSING."""
    for part in key.split("."):
        if not isinstance(d, dict) or part not in d:
            return _MISSING
        d = d[part]
    return d


def make_dir(key: str, path: Any, *subdirs: str, probe: bool = False) -> Path:
    """The folder a setting names (`key`, e.g. out_dir), made with `subdirs` inside it and, with `probe`, a file
    written and removed there; any OSError is a one-line ConfigError naming the setting."""
    out = Path(str(path))
    try:
        out.mkdir(parents=True, exist_ok=True)
        for sub in subdirs:
            (out / sub).mkdir(exist_ok=True)
        if probe:  # a folder that exists may still refuse a file (read-only mount, no space)
            (out / ".write_probe").write_bytes(b"")
            (out / ".write_probe").unlink()
    except OSError as e:
        raise ConfigError(f"{key}: cannot write to {path!r} ({e.strerror})") from None
    return out


def names(value: Any) -> list[str] | None:
    """A list-of-names setting whose default is null: None stays None, a string is a comma-separated list
    (`scenarios=pick,place`; iterated as it is, `scenarios=pick` would be four one-letter names)."""
    if value is None:
        return None
    return [str(v) for v in (_comma_list(value) if isinstance(value, str) else value)]


def size_setting(key: str, value: object, example: str) -> tuple[int, int]:
    """A `WxH` setting (e.g. grid=512x512) as positive (width, height), or a one-line ConfigError naming `key`."""
    try:
        w, h = (int(x) for x in str(value).lower().split("x"))
    except ValueError:
        w = h = 0
    if w < 1 or h < 1:
        raise ConfigError(f"{key}: expected a positive WxH (e.g. {example}), got {value!r}")
    return w, h


def load_config(defaults: str | Path, argv: list[str]) -> DictConfig:
    """Defaults (a YAML file under configs/, or YAML text; struct: unknown keys are errors) merged with the command
    line (`dotlist`). A top-level mapping that is empty in the defaults (`backend_kwargs: {}`) is a free-form
    section: its keys are checked by whoever reads it (a backend checks its own options)."""
    base, text = _defaults(defaults)
    if any(a in ("-h", "--help") for a in argv):
        raise HelpRequested(text)
    OmegaConf.set_struct(base, True)
    for key in base:
        node = base[key]
        if isinstance(node, DictConfig) and len(node) == 0:
            OmegaConf.set_struct(node, False)
    args = dotlist(argv)
    try:
        cli = OmegaConf.from_dotlist(args)
        layers = [base]
        if "presets" in base:  # `preset=NAME` applies presets.NAME between the defaults and the command line
            name = cli.get("preset", base.get("preset"))
            if name not in base.presets:
                raise ConfigError(f"preset: unknown preset {name!r}; known: {', '.join(base.presets)}")
            layers.append(base.presets[name])
        given = OmegaConf.to_container(cli, resolve=False)
        _check_shapes(OmegaConf.merge(*layers), given)
        cfg = OmegaConf.merge(*layers, OmegaConf.create(given))
    except ConfigError:
        raise
    except Exception as e:  # omegaconf raises several types for unknown keys / bad syntax
        key = getattr(e, "full_key", None) or _unparsable(args) or str(e).splitlines()[0]
        raise ConfigError(f"{key}: not a valid setting ({type(e).__name__})") from None
    assert isinstance(cfg, DictConfig)
    return cfg


# bool settings whose reader also takes a path (train's `resume=<checkpoint folder>`)
BOOL_OR_PATH = frozenset({"resume"})
# number settings whose reader also takes a word: the bench's operating point chosen on val, the cache's auto size
NUMBER_OR_WORD = {"threshold": "val", "a_threshold": "val", "b_threshold": "val", "tower_cache_mb": "auto"}


def _unparsable(args: list[str]) -> str | None:
    """The key of the first setting whose value does not parse on its own (`num_episodes=[1`), or None."""
    for a in args:
        try:
            OmegaConf.from_dotlist([a])
        except Exception:  # noqa: BLE001 - any parse failure names this argument
            return a.partition("=")[0]
    return None


def _comma_list(value: str) -> list[Any]:
    """`a,b` as the list `[a,b]` would be: numbers stay numbers (`pair_shares=0.2,0.5`); text YAML cannot read in
    brackets is split on its commas as it is."""
    try:
        return list(OmegaConf.to_container(OmegaConf.from_dotlist([f"v=[{value}]"]))["v"])  # type: ignore[index]
    except Exception:  # noqa: BLE001 - any YAML problem: plain names
        return [v.strip() for v in value.split(",") if v.strip()]


def _number_or_word(key: str, value: str) -> bool:
    """Whether a string given for a number setting is one (`inf`), an interpolation, or the word its reader takes."""
    if value.startswith("${") or value == NUMBER_OR_WORD.get(key):
        return True
    try:
        float(value)
    except ValueError:
        return False
    return True


def _check_shapes(defaults: Any, given: Any, prefix: str = "") -> None:
    """The command line's values against the shapes of their defaults, as one-line errors before any reader sees
    them (a reader would iterate a bool, or call int() on a list): a number or bool where the default is a list
    (`baselines=false`), a list or mapping where it is a number or bool (`seed=[1]`), anything but true/false where
    it is a bool (`draw_index=maybe`), a word where it is a number (`seed=abc`; NUMBER_OR_WORD lists the words
    readers take). A string where the default is a list is a comma-separated list
    (`cameras=front,side`; `cameras=front` would otherwise read as five one-letter views); null, and a string
    where the default is text or null, are left to the reader (`pair_shares=null`, `shards=DIR` or a list).
    `given`: the command line as plain containers, interpolations unresolved; rewritten in place."""
    for key, value in list(given.items()):
        default = defaults.get(key) if isinstance(defaults, DictConfig) else None
        name = f"{prefix}{key}"
        if isinstance(value, dict) and not isinstance(default, (bool, int, float)):
            _check_shapes(default, value, f"{name}.")
        elif isinstance(default, ListConfig):
            if isinstance(value, (bool, int, float)):
                example = ",".join(map(str, default)) if len(default) else "a,b"
                raise ConfigError(f"{name}: expected a list (e.g. '{name}=[{example}]' or '{name}=[]'), got {value!r}")
            if isinstance(value, str) and not value.startswith("${"):
                given[key] = _comma_list(value)
        elif isinstance(default, (bool, int, float)) and isinstance(value, (list, dict)):
            raise ConfigError(f"{name}: expected one value, got {'a list' if isinstance(value, list) else 'a mapping'}")
        elif isinstance(default, bool) and value is not None and not isinstance(value, bool):
            if not (isinstance(value, str) and key in BOOL_OR_PATH):
                raise ConfigError(f"{name}: expected true or false, got {value!r}")
        elif isinstance(default, (int, float)) and isinstance(value, str) and not _number_or_word(key, value):
            word = NUMBER_OR_WORD.get(key)
            raise ConfigError(f"{name}: expected {word + ' or ' if word else ''}a number, got {value!r}")


def cli_main(fn: Callable[[list[str]], int], doc: str | None = None) -> None:
    try:
        code = fn(sys.argv[1:])
    except HelpRequested as h:
        try:
            print(((doc or "").strip() + "\n\nSettings (key=value, --key value or --key=value):\n\n" + str(h)).strip())
        except BrokenPipeError:  # `--help | head`: the reader has gone, which is fine
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 0
    except (ValueError, OSError) as e:  # ConfigError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print("error: interrupted; rerun the same command to resume", file=sys.stderr)
        code = 130
    sys.exit(code)
