"""ACT configuration: sizes of the CNN backbone, the CVAE and the transformer, chunking and ensembling.

Sized to train on 2 CPU cores within 45 minutes per task family (~1 M parameters, 64 px views). The
normalisation statistics of the training demonstrations travel with the configuration (act.json).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

STATE_DIM = 9  # ee_pos (3), ee_quat (4), finger width, gripper command
ACTION_DIM = 10  # target position (3), rotation as the first two columns of its matrix (6), gripper (1)


@dataclass
class ACTConfig:
    cameras: list[str] = field(default_factory=lambda: ["front", "side"])
    image_size: int = 64  # square views; other sizes are resized
    state_dim: int = STATE_DIM
    action_dim: int = ACTION_DIM
    chunk_size: int = 20  # k: actions predicted per query
    backbone_channels: list[int] = field(default_factory=lambda: [16, 32, 64, 128])  # stride-2 conv stages
    keypoints: int = 0  # K > 0: a spatial-softmax token of K image keypoints per view (modeling_act.Backbone)
    dim_model: int = 128
    n_heads: int = 4
    dim_feedforward: int = 256
    n_encoder_layers: int = 2
    # The reference implementation builds 7 decoder layers but returns only the first layer's output
    # (lerobot therefore sets 1); here the count is explicit and every layer is used.
    n_decoder_layers: int = 1
    n_vae_encoder_layers: int = 2
    latent_dim: int = 32
    dropout: float = 0.1
    kl_weight: float = 10.0
    # > 0: two more decoder queries predict where the demonstration grasps and where it tilts (modeling_act), an
    # auxiliary L1 of this weight; a policy that must close on a vessel is told, while it learns, where the vessel is
    aux_weight: float = 0.0
    temporal_ensemble_coeff: float | None = 0.01  # w_i = exp(-coeff * i), i = 0 the oldest; None: run chunks open loop
    stats: dict[str, list[float]] = field(default_factory=dict)  # state/action mean and std of the demos

    def __post_init__(self) -> None:
        for k in (
            "image_size",
            "chunk_size",
            "dim_model",
            "n_heads",
            "n_encoder_layers",
            "n_decoder_layers",
            "latent_dim",
        ):
            if int(getattr(self, k)) < 1:
                raise ValueError(f"act.{k}: must be a positive integer, got {getattr(self, k)!r}")
        if isinstance(self.aux_weight, bool) or not isinstance(self.aux_weight, (int, float)) or self.aux_weight < 0:
            raise ValueError(f"act.aux_weight: must be a number >= 0 (0: none), got {self.aux_weight!r}")
        if int(self.keypoints) < 0:
            raise ValueError(f"act.keypoints: must be 0 (none) or a positive integer, got {self.keypoints!r}")
        if self.dim_model % self.n_heads:
            raise ValueError(f"act.dim_model: {self.dim_model} is not divisible by n_heads={self.n_heads}")

    def stat_arrays(self) -> tuple[Any, Any, Any, Any]:
        """(state mean, state std, action mean, action std) as arrays: a policy normalises its proprio with the
        first two and un-normalises the model's actions with the last two."""
        import numpy as np

        s = self.stats
        return (
            np.asarray(s["state_mean"], np.float32),
            np.asarray(s["state_std"], np.float32),
            np.asarray(s["action_mean"]),
            np.asarray(s["action_std"]),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ACTConfig":
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"act config: unknown keys {unknown}")
        return cls(**d)

    def save(self, path: Path) -> None:
        from labrobfail_vlm.io import atomic_write_json

        atomic_write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: Path) -> "ACTConfig":
        return cls.from_dict(json.loads(Path(path).read_text()))
