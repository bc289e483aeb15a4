"""The sim-pretrained vision tower shipped with the project, and how the tiny Qwen3-VL takes it.

`make tower` (labrobfail-pretrain-tower, labrobfail_vlm/train/tower.py) writes `tower.safetensors` (the vision
tower and merger of a Qwen3-VL, keys as in `model.visual`) and `tower.json` (its vision config, data, held-out
accuracy, command and sha256); `labrobfail_vlm/assets/tower/` ships one. `train.py preset=tiny` builds its random
model with that tower in place (`tower=shipped`, the preset's default), `tower=scratch` keeps the random tower,
and `tower=DIR` takes another one. A real Qwen3-VL checkpoint keeps its own tower.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.io import sha256_file

TOWER_FILE, CARD_FILE = "tower.safetensors", "tower.json"
CHOICES = ("shipped", "scratch")


def shipped_dir() -> Path:
    return Path(str(resources.files("labrobfail_vlm") / "assets" / "tower"))


def resolve(spec: str | None) -> Path | None:
    """`tower` setting -> the folder holding the tower, or None for a random ("scratch") tower."""
    if spec is None or str(spec) == "scratch":
        return None
    return shipped_dir() if str(spec) == "shipped" else Path(str(spec))


def read_card(folder: Path) -> dict[str, Any]:
    """tower.json after checking that tower.safetensors is there and is the file the card describes."""
    card_f, weights = folder / CARD_FILE, folder / TOWER_FILE
    if not card_f.is_file() or not weights.is_file():
        raise ConfigError(
            f"tower: {folder} lacks {CARD_FILE} or {TOWER_FILE} (make tower writes them; "
            "tower=scratch trains the tower from random weights)"
        )
    try:
        card = json.loads(card_f.read_text())
        want = str(card["sha256"])
        card["vision_config"]["depth"]
    except (OSError, ValueError, KeyError, TypeError):
        raise ConfigError(f"tower: {card_f} is not a tower card (vision_config, sha256)") from None
    if sha256_file(weights) != want:
        raise ConfigError(f"tower: {weights} does not match the sha256 in {card_f} (a different or damaged file)")
    return card


def vision_overrides(card: dict[str, Any]) -> dict[str, Any]:
    """The Qwen3-VL vision config keys the tower was built with (the tiny model's `vision` argument)."""
    skip = {
        "out_hidden_size",
        "model_type",
        "transformers_version",
        "architectures",
        "dtype",
        "torch_dtype",
        "output_attentions",
        "output_hidden_states",
        "return_dict",
        "initializer_range",
    }
    return {k: v for k, v in card["vision_config"].items() if k not in skip and not k.startswith("_")}


def load_visual(visual: Any, folder: Path) -> None:
    """Copy the tower's weights into a Qwen3-VL vision tower module (`model.visual`, every tensor, same shapes)."""
    from safetensors.torch import load_file

    state = load_file(str(folder / TOWER_FILE))
    try:
        missing, unexpected = visual.load_state_dict(state, strict=False)
    except RuntimeError:  # a shape mismatch: another tower size than the card says
        missing, unexpected = ["(shapes differ)"], []
    if missing or unexpected:
        raise ConfigError(
            f"tower: {folder / TOWER_FILE} does not fit the model's vision tower (missing "
            f"{missing[:2]}, unexpected {unexpected[:2]})"
        )


def raised_saturation(ref: dict[str, Any] | None) -> bool:
    """Whether the tower a run started from (train_summary.json's `tower`: path and sha256) was pretrained with colour
    augmentation that could raise a pixel's saturation, read from its card's last stage (the three stages of `make
    tower` share the setting). True where the card cannot tell: no augment section, or a tower no longer at its path
    (the shipped one replaced since), so a page never claims more than it knows; False for a random tower."""
    from labrobfail_vlm.augment import AugmentConfig

    folder = resolve(str(ref["path"])) if ref else None
    if not ref or folder is None:
        return False
    try:
        card = read_card(folder)  # the card of the weights now at that path
    except ConfigError:
        return True
    training = card.get("training")
    aug = training.get("augment") if isinstance(training, dict) else None
    if not isinstance(aug, dict) or not aug or card["sha256"] != ref.get("sha256"):
        return True
    try:
        return AugmentConfig.from_section({"hue": None, **aug}).raise_saturation
    except ValueError:  # a card this version cannot read
        return True
