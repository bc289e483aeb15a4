"""OmegaConf loading shared by every entry point: YAML defaults + command-line dotlist, one-line errors.

Entry points call `cli_main(fn)`: a ConfigError or ValueError becomes `error: <message>` on stderr
and exit code 2, never a traceback.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

from omegaconf import DictConfig, OmegaConf

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


class ConfigError(ValueError):
    """A bad configuration value or input; the message names the field or file."""


def load_config(defaults: str | Path, dotlist: list[str]) -> DictConfig:
    """Defaults from a YAML file under configs/ (struct: unknown keys are errors) merged with `key=value` args.
    A top-level mapping that is empty in the defaults (`backend_kwargs: {}`) is a free-form section: its keys
    are checked by whoever reads it (a backend checks its own options)."""
    base = OmegaConf.load(CONFIG_DIR / defaults if not Path(defaults).is_absolute() else defaults)
    OmegaConf.set_struct(base, True)
    for key in base:
        node = base[key]
        if isinstance(node, DictConfig) and len(node) == 0:
            OmegaConf.set_struct(node, False)
    try:
        cli = OmegaConf.from_dotlist(dotlist)
        layers = [base]
        if "presets" in base:  # `preset=NAME` applies presets.NAME between the defaults and the command line
            name = cli.get("preset", base.get("preset"))
            if name not in base.presets:
                raise ConfigError(f"preset: unknown preset {name!r}; known: {', '.join(base.presets)}")
            layers.append(base.presets[name])
        cfg = OmegaConf.merge(*layers, cli)
    except ConfigError:
        raise
    except Exception as e:  # omegaconf raises several types for unknown keys / bad syntax
        key = getattr(e, "full_key", None) or str(e).splitlines()[0]
        raise ConfigError(f"{key}: not a valid setting ({type(e).__name__})") from None
    assert isinstance(cfg, DictConfig)
    return cfg


def cli_main(fn: Callable[[list[str]], int]) -> None:
    try:
        code = fn(sys.argv[1:])
    except (ValueError, OSError) as e:  # ConfigError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print("error: interrupted; rerun the same command to resume", file=sys.stderr)
        code = 130
    sys.exit(code)
