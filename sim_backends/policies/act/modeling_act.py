"""ACT in plain torch: a CVAE whose decoder is a transformer predicting a chunk of k actions.

    training:   z ~ q(z | state, action chunk)   (the CVAE encoder: a transformer over [CLS, state, actions])
    both:       encoder tokens = [z, state, CNN features of every camera view] (+ positional embeddings)
                decoder: k learned queries cross-attend to the encoder -> k actions
    inference:  z = 0 (the prior's mean); chunks are blended over time by `TemporalEnsembler`

The backbone is a small CNN written here (torchvision, hence ResNet-18, is not available on the project's
machines): four stride-2 3x3 conv stages with GroupNorm, so a 64 px view becomes 4x4 feature tokens. Loss: L1
on the (normalised) actions of the chunk, masked past the episode's end, plus kl_weight x KL(q || N(0, I)).

Optional `keypoints` (K > 0): a spatial softmax over the backbone's second-to-last stage (twice the final
resolution) turns K learned feature maps into K expected image positions (Levine et al. 2016, robomimic's default
for visuomotor BC), one extra encoder token per view. The 16 px feature tokens place an 8 px vessel only to within
a token; the soft-argmax is continuous, so the decoder can read where a vessel is to a fraction of a token.

Optional `aux_weight` > 0: two more decoder queries beside the k action queries, whose outputs a linear head reads
as where the demonstration closes the gripper (the grasp) and where it turns the hand furthest from its first
orientation (a pour's tilt), each relative to the hand, in units of AUX_SCALE metres. Their L1, times
`aux_weight`, joins the loss: the action queries attend to them, and the picture has to say where the vessel stands
(a pour ACT fitted on actions alone put its grasp 1.9 cm from its own demonstrations', against a 3.9 cm spread of
the grasps themselves; with these queries 1.3 cm: scripts/probe_act.py, docs/EXPERIMENTS.md, 27 Nov). At inference
they cost two decoder tokens and are not used.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from sim_backends.policies.act.configuration_act import ACTConfig

AUX_POINTS = 2  # the grasp, the tilt (sim_backends/policies/act/data.py: key_points)
AUX_SCALE = 0.05  # m: one unit of an auxiliary target


def sine_table(n: int, dim: int) -> Tensor:
    """1-D sinusoidal positional embeddings (n, dim)."""
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    out = torch.zeros(n, dim)
    out[:, 0::2] = torch.sin(pos * div)
    out[:, 1::2] = torch.cos(pos * div)[:, : dim // 2]
    return out


def sine_2d(h: int, w: int, dim: int) -> Tensor:
    """2-D sinusoidal embeddings of an h x w feature map, flattened row-major: (h*w, dim)."""
    half = dim // 2
    ys, xs = sine_table(h, half), sine_table(w, dim - half)
    return torch.cat([ys[:, None, :].expand(h, w, half), xs[None, :, :].expand(h, w, dim - half)], -1).reshape(
        h * w, dim
    )


class Backbone(nn.Module):
    def __init__(self, channels: list[int], dim: int, keypoints: int = 0):
        super().__init__()
        layers: list[nn.Module] = []
        cin = 3
        for c in channels:
            layers += [nn.Conv2d(cin, c, 3, stride=2, padding=1), nn.GroupNorm(min(8, c), c), nn.ReLU(inplace=True)]
            cin = c
        self.net = nn.Sequential(*layers)
        self.proj = nn.Conv2d(cin, dim, 1)
        self.keypoints = int(keypoints)
        if self.keypoints:
            mid = channels[-2] if len(channels) > 1 else 3
            self.kp_maps = nn.Conv2d(mid, self.keypoints, 1)
            self.kp_proj = nn.Linear(2 * self.keypoints, dim)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        """(B, 3, H, W) in [0, 1] -> feature map (B, dim, H/2^n, W/2^n) and, with keypoints, (B, dim) tokens."""
        mid = self.net[:-3](x * 2.0 - 1.0)  # the input of the last stage (each stage is conv, norm, relu)
        feats = self.proj(self.net[-3:](mid))
        return feats, self.kp_proj(spatial_softmax(self.kp_maps(mid))) if self.keypoints else None


def spatial_softmax(maps: Tensor) -> Tensor:
    """(B, K, h, w) -> (B, 2K): the expected x of each map's softmax, then the expected y, in [-1, 1] (pixel
    centres)."""
    b, k, h, w = maps.shape
    p = torch.softmax(maps.flatten(2), -1).reshape(b, k, h, w)
    ys = torch.linspace(-1 + 1 / h, 1 - 1 / h, h, device=maps.device, dtype=maps.dtype)
    xs = torch.linspace(-1 + 1 / w, 1 - 1 / w, w, device=maps.device, dtype=maps.dtype)
    return torch.cat([(p.sum(2) * xs).sum(-1), (p.sum(3) * ys).sum(-1)], -1)


class ACTModel(nn.Module):
    def __init__(self, cfg: ACTConfig):
        super().__init__()
        self.cfg = cfg
        d = cfg.dim_model

        def encoder(n: int) -> nn.TransformerEncoder:
            layer = nn.TransformerEncoderLayer(d, cfg.n_heads, cfg.dim_feedforward, cfg.dropout, batch_first=True)
            return nn.TransformerEncoder(layer, n, enable_nested_tensor=False)

        # CVAE encoder (training only)
        self.vae_cls = nn.Parameter(torch.zeros(1, 1, d))
        self.vae_state = nn.Linear(cfg.state_dim, d)
        self.vae_action = nn.Linear(cfg.action_dim, d)
        self.vae_encoder = encoder(cfg.n_vae_encoder_layers)
        self.vae_out = nn.Linear(d, 2 * cfg.latent_dim)
        self.register_buffer("vae_pos", sine_table(cfg.chunk_size + 2, d), persistent=False)
        # observation encoder
        self.backbone = Backbone(list(cfg.backbone_channels), d, cfg.keypoints)
        self.latent_in = nn.Linear(cfg.latent_dim, d)
        self.state_in = nn.Linear(cfg.state_dim, d)
        self.token_pos = nn.Parameter(torch.zeros(2, d))  # learned embeddings of the latent and state tokens
        self.camera_embed = nn.Parameter(torch.zeros(len(cfg.cameras), d))
        self.encoder = encoder(cfg.n_encoder_layers)
        # decoder: k queries
        layer = nn.TransformerDecoderLayer(d, cfg.n_heads, cfg.dim_feedforward, cfg.dropout, batch_first=True)
        self.decoder = nn.TransformerDecoder(layer, cfg.n_decoder_layers)
        self.n_aux = AUX_POINTS if cfg.aux_weight > 0 else 0
        self.queries = nn.Parameter(torch.randn(cfg.chunk_size + self.n_aux, d) * 0.02)
        self.action_head = nn.Linear(d, cfg.action_dim)
        self.aux_head = nn.Linear(d, 3) if self.n_aux else None

    def encode_latent(self, state: Tensor, actions: Tensor, pad: Tensor) -> tuple[Tensor, Tensor]:
        """(mu, logvar) of q(z | state, actions); `pad` (B, k) is True past the episode's end."""
        b = state.shape[0]
        x = torch.cat([self.vae_cls.expand(b, -1, -1), self.vae_state(state)[:, None], self.vae_action(actions)], 1)
        x = x + self.vae_pos[None]
        mask = torch.cat([torch.zeros(b, 2, dtype=torch.bool, device=pad.device), pad], 1)
        h = self.vae_encoder(x, src_key_padding_mask=mask)[:, 0]
        mu, logvar = self.vae_out(h).chunk(2, -1)
        return mu, logvar

    def forward(self, images: Tensor, state: Tensor, z: Tensor) -> Tensor:
        """images (B, V, 3, H, W) in [0, 1], state (B, state_dim), z (B, latent) -> actions (B, k, action_dim)."""
        return self.decode(images, state, z)[0]

    def decode(self, images: Tensor, state: Tensor, z: Tensor) -> tuple[Tensor, Tensor | None]:
        """The actions and, with `aux_weight`, the auxiliary points (B, AUX_POINTS, 3)."""
        b, v = images.shape[:2]
        feats, kp = self.backbone(images.flatten(0, 1))  # (B*V, d, h, w), (B*V, d) or None
        _, d, h, w = feats.shape
        tokens = feats.flatten(2).transpose(1, 2).reshape(b, v, h * w, d)
        tokens = tokens + sine_2d(h, w, d).to(tokens)[None, None]
        if kp is not None:  # one keypoint token per view, after its feature tokens
            tokens = torch.cat([tokens, kp.reshape(b, v, 1, d)], 2)
        tokens = tokens + self.camera_embed[None, :v, None]
        x = torch.cat(
            [
                (self.latent_in(z) + self.token_pos[0])[:, None],
                (self.state_in(state) + self.token_pos[1])[:, None],
                tokens.flatten(1, 2),
            ],
            1,
        )
        memory = self.encoder(x)
        out = self.decoder(self.queries[None].expand(b, -1, -1), memory)
        k = self.cfg.chunk_size
        aux = self.aux_head(out[:, k:]) if self.aux_head is not None else None
        return self.action_head(out[:, :k]), aux

    def loss(
        self, images: Tensor, state: Tensor, actions: Tensor, pad: Tensor, points: Tensor | None = None
    ) -> tuple[Tensor, dict[str, float]]:
        """`points` (B, AUX_POINTS, 3): the auxiliary targets, needed when `aux_weight` > 0."""
        mu, logvar = self.encode_latent(state, actions, pad)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
        pred, aux = self.decode(images, state, z)
        keep = (~pad).float()[..., None]
        l1 = (F.l1_loss(pred, actions, reduction="none") * keep).sum() / (keep.sum() * actions.shape[-1]).clamp(min=1)
        kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp())).sum(-1).mean()
        total = l1 + self.cfg.kl_weight * kl
        parts = {"l1": float(l1.detach()), "kl": float(kl.detach())}
        if aux is not None:
            if points is None:
                raise ValueError("act: aux_weight > 0 needs the auxiliary points of every sample")
            aux_l1 = F.l1_loss(aux, points)
            total = total + self.cfg.aux_weight * aux_l1
            parts["aux_l1"] = float(aux_l1.detach())
        return total, {"loss": float(total.detach())} | parts

    @torch.no_grad()
    def predict(self, images: Tensor, state: Tensor) -> Tensor:
        z = torch.zeros(state.shape[0], self.cfg.latent_dim, device=state.device, dtype=state.dtype)
        return self(images, state, z)


class TemporalEnsembler:
    """ACT's temporal ensembling: every query predicts a chunk a[t..t+k-1]; the action executed at t is the
    weighted mean of every chunk's prediction for t, with weights exp(-coeff * i), i = 0 for the oldest chunk."""

    def __init__(self, chunk_size: int, coeff: float):
        self.k, self.coeff = chunk_size, float(coeff)
        self.chunks: deque[tuple[int, np.ndarray]] = deque()
        self.t = 0

    def reset(self) -> None:
        self.chunks.clear()
        self.t = 0

    def __call__(self, chunk: np.ndarray) -> np.ndarray:
        """Add the chunk predicted at the current step; the action to execute now."""
        self.chunks.append((self.t, np.asarray(chunk, float)))
        while self.chunks and self.chunks[0][0] <= self.t - self.k:
            self.chunks.popleft()
        preds = [c[self.t - t0] for t0, c in self.chunks]  # oldest first
        w = np.exp(-self.coeff * np.arange(len(preds)))
        self.t += 1
        return (w[:, None] * np.stack(preds)).sum(0) / w.sum()


class ChunkRunner:
    """Without ensembling: query once, execute the k actions of the chunk, query again."""

    def __init__(self, chunk_size: int):
        self.k = chunk_size
        self.chunk: np.ndarray | None = None
        self.i = 0

    def reset(self) -> None:
        self.chunk, self.i = None, 0

    def needs_query(self) -> bool:
        return self.chunk is None or self.i >= self.k

    def __call__(self, chunk: np.ndarray | None) -> np.ndarray:
        if chunk is not None:
            self.chunk, self.i = np.asarray(chunk, float), 0
        assert self.chunk is not None, "query first"
        self.i += 1
        return self.chunk[self.i - 1]
