"""MUSIQ no-reference image quality (Ke et al., "MUSIQ: Multi-scale Image Quality Transformer", ICCV 2021).

Loads the IQA-PyTorch (pyiqa) conversions of the official JAX/Flax checkpoints from a local file only
(``musiq_koniq_ckpt-*.pth``, ``musiq_spaq_ckpt-*.pth``, ``musiq_paq2piq_ckpt-*.pth``,
``musiq_ava_ckpt-*.pth``); nothing is downloaded. Module and parameter names follow pyiqa's
``MUSIQ`` so its state dicts load with strict key matching.

Pipeline (higher score = better quality):
  1. image in [0, 1] -> [-1, 1];
  2. multi-scale representation: the image resized (aspect ratio kept, bicubic as in pyiqa) so its
     longer side is 224 and 384, plus the original resolution; each scale is cut into 32x32 patches
     (TF "SAME" zero padding);
  3. every patch gets a hash-based 2-D spatial position embedding (its row/column mapped onto a
     10x10 grid) and a scale embedding (0, 1, 2 for 224, 384, original);
  4. patch tokens = ResNet-style stem (weight-standardised 7x7/2 conv, GroupNorm, ReLU, 3x3/2 max pool,
     one bottleneck block) -> flatten (HWC order) -> linear embedding;
  5. [CLS] + tokens -> 14-layer pre-norm transformer encoder -> LayerNorm -> head on [CLS]:
     a scalar (KonIQ / SPAQ / PaQ-2-PiQ models, roughly 0..100) or a 10-way softmax whose mean
     sum_k k p_k is the score (AVA model, 1..10).

The official pipeline pads each scale to a fixed sequence length and masks the padding out of the
attention; padded tokens are simply not created here, which gives the same [CLS] output.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from d2turb.errors import D2TurbError
from d2turb.eval.vgg import load_state_dict_file
from d2turb.io import cache_dir, check_image_tensor

ENV_VAR = "D2TURB_MUSIQ_WEIGHTS"
# Searched (in this order) in a folder given by D2TURB_MUSIQ_WEIGHTS and in $D2TURB_CACHE_DIR/musiq/.
FILE_NAMES = ("musiq.safetensors", "musiq.pth", "musiq_koniq_ckpt-e95806b9.pth")
FILE_GLOB = "musiq_koniq_ckpt*.pth"


@dataclass(frozen=True)
class MUSIQConfig:
    """Architecture; the defaults are the published MUSIQ (official run_predict_image.py / pyiqa)."""

    hidden_size: int = 384
    num_layers: int = 14
    num_heads: int = 6
    mlp_dim: int = 1152
    patch_size: int = 32
    grid_size: int = 10  # hash-based spatial embedding grid G (G x G entries)
    longer_side_lengths: tuple[int, ...] = (224, 384)
    use_original_resolution: bool = True
    stem_width: int = 64  # RESNET_TOKEN_DIM; a multiple of 32 (GroupNorm with 32 groups)
    num_classes: int | None = None  # 1 (regression) or 10 (AVA); None = read from the checkpoint

    @property
    def num_scales(self) -> int:
        return len(self.longer_side_lengths) + int(self.use_original_resolution)


# ----------------------------------------------------------------------------- preprocessing


def _same_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """TensorFlow "SAME" padding (before, after) along one axis."""
    total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def resized_size(h: int, w: int, longer_side: int) -> tuple[int, int]:
    """Aspect-preserving size whose longer side is ``longer_side`` (round half to even, as tf.round)."""
    ratio = longer_side / max(h, w)
    return max(round(h * ratio), 1), max(round(w * ratio), 1)  # >= 1 only matters for degenerate strips


def hashed_position_index(count_h: int, count_w: int, grid_size: int = 10) -> torch.Tensor:
    """(count_h * count_w,) row-major hash of each patch onto the G x G grid: G * row' + col'.

    row' = floor(i * (G / count_h)) computed in float32 like TF/torch nearest-neighbour resizing of
    ``arange(G)`` to ``count`` samples (clamped to G - 1).
    """

    def axis(count: int) -> torch.Tensor:
        scale = torch.tensor(grid_size / count, dtype=torch.float32)
        return torch.floor(torch.arange(count, dtype=torch.float32) * scale).long().clamp(max=grid_size - 1)

    return (axis(count_h)[:, None] * grid_size + axis(count_w)[None, :]).reshape(-1)


def extract_patches(image: torch.Tensor, patch_size: int) -> tuple[torch.Tensor, int, int]:
    """(B, C, H, W) -> (B, nh * nw, C, P, P) non-overlapping patches in row-major order, TF "SAME" zero padding."""
    _, c, h, w = image.shape
    (top, bottom), (left, right) = _same_padding(h, patch_size, patch_size), _same_padding(w, patch_size, patch_size)
    x = F.pad(image, (left, right, top, bottom))
    nh, nw = x.shape[2] // patch_size, x.shape[3] // patch_size
    x = x.reshape(x.shape[0], c, nh, patch_size, nw, patch_size).permute(0, 2, 4, 1, 3, 5)
    return x.reshape(x.shape[0], nh * nw, c, patch_size, patch_size), nh, nw


def multiscale_patches(image: torch.Tensor, config: MUSIQConfig = MUSIQConfig()):
    """Multi-scale patch representation of ``image`` (B, 3, H, W) (already mapped to [-1, 1]).

    Returns ``patches`` (B, N, 3, P, P), ``spatial`` (N,) hashed position indices in [0, G^2) and
    ``scale`` (N,) scale ids, scales ordered by increasing longer side, the original resolution last.
    """
    _, _, h, w = image.shape
    images = []
    for length in sorted(config.longer_side_lengths):
        size = resized_size(h, w, length)
        images.append(F.interpolate(image, size=size, mode="bicubic", align_corners=False))
    if config.use_original_resolution:
        images.append(image)
    patches, spatial, scale = [], [], []
    for scale_id, img in enumerate(images):
        p, nh, nw = extract_patches(img, config.patch_size)
        patches.append(p)
        spatial.append(hashed_position_index(nh, nw, config.grid_size))
        scale.append(torch.full((nh * nw,), scale_id, dtype=torch.long))
    return torch.cat(patches, 1), torch.cat(spatial).to(image.device), torch.cat(scale).to(image.device)


# ----------------------------------------------------------------------------- network (pyiqa key names)


class _StdConv(nn.Conv2d):
    """Conv with weight standardisation and TF "SAME" padding (BiT-style ResNet stem of MUSIQ)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k, s = self.kernel_size[0], self.stride[0]
        (top, bottom), (left, right) = _same_padding(x.shape[2], k, s), _same_padding(x.shape[3], k, s)
        weight = self.weight - self.weight.mean((1, 2, 3), keepdim=True)
        weight = weight / (weight.std((1, 2, 3), keepdim=True) + 1e-5)  # unbiased std, as pyiqa
        return F.conv2d(F.pad(x, (left, right, top, bottom)), weight, None, self.stride)


class _Bottleneck(nn.Module):
    def __init__(self, width: int, out: int):
        super().__init__()
        self.conv1, self.gn1 = _StdConv(width, width, 1, bias=False), nn.GroupNorm(32, width, eps=1e-4)
        self.conv2, self.gn2 = _StdConv(width, width, 3, bias=False), nn.GroupNorm(32, width, eps=1e-4)
        self.conv3, self.gn3 = _StdConv(width, out, 1, bias=False), nn.GroupNorm(32, out, eps=1e-4)
        self.conv_proj, self.gn_proj = _StdConv(width, out, 1, bias=False), nn.GroupNorm(32, out, eps=1e-4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = self.gn_proj(self.conv_proj(x))
        x = F.relu(self.gn1(self.conv1(x)))
        x = F.relu(self.gn2(self.conv2(x)))
        return F.relu(self.gn3(self.conv3(x)) + identity)


class _Attention(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.query, self.key, self.value, self.out = (nn.Linear(dim, dim) for _ in range(4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = (
            proj(x).reshape(b, n, self.heads, d // self.heads).transpose(1, 2)
            for proj in (self.query, self.key, self.value)
        )
        y = F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d_head)) v
        return self.out(y.transpose(1, 2).reshape(b, n, d))


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))  # exact (erf) GELU, as pyiqa


class _EncoderBlock(nn.Module):
    def __init__(self, dim: int, mlp_dim: int, heads: int):
        super().__init__()
        self.norm1, self.attention = nn.LayerNorm(dim, eps=1e-6), _Attention(dim, heads)
        self.norm2, self.mlp = nn.LayerNorm(dim, eps=1e-6), _Mlp(dim, mlp_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attention(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class _PositionEmbedding(nn.Module):
    def __init__(self, grid_size: int, dim: int):
        super().__init__()
        self.position_emb = nn.Parameter(torch.randn(1, grid_size * grid_size, dim) * 0.02)


class _ScaleEmbedding(nn.Module):
    def __init__(self, num_scales: int, dim: int):
        super().__init__()
        self.scale_emb = nn.Parameter(torch.randn(num_scales, dim) * 0.02)


class _Encoder(nn.Module):
    def __init__(self, config: MUSIQConfig):
        super().__init__()
        d = config.hidden_size
        self.posembed_input = _PositionEmbedding(config.grid_size, d)
        self.scaleembed_input = _ScaleEmbedding(config.num_scales, d)
        self.cls = nn.Parameter(torch.zeros(1, 1, d))
        self.encoder_norm = nn.LayerNorm(d, eps=1e-6)
        self.transformer = nn.ModuleDict(
            {f"encoderblock_{i}": _EncoderBlock(d, config.mlp_dim, config.num_heads) for i in range(config.num_layers)}
        )

    def forward(self, tokens: torch.Tensor, spatial: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        x = tokens + self.posembed_input.position_emb[0, spatial] + self.scaleembed_input.scale_emb[scale]
        x = torch.cat([self.cls.expand(x.shape[0], -1, -1), x], dim=1)
        for block in self.transformer.values():
            x = block(x)
        return self.encoder_norm(x)


def _load_state(path: Path) -> dict[str, torch.Tensor]:
    state = load_state_dict_file(path, "MUSIQ weights")
    for wrapper in ("params", "model"):
        if set(state) == {wrapper}:
            state = state[wrapper]
    return {k.removeprefix("module."): v for k, v in state.items()}


def _num_classes(state: dict[str, torch.Tensor], path: Path) -> int:
    if "head.weight" in state:
        return state["head.weight"].shape[0]
    if "head.0.weight" in state:
        return state["head.0.weight"].shape[0]
    raise D2TurbError(
        f"{path} is not a MUSIQ checkpoint (no head.weight / head.0.weight; "
        f"first keys: {', '.join(list(state)[:3]) or 'none'})"
    )


class MUSIQ(nn.Module):
    """MUSIQ quality predictor; ``forward(image (B, 3, H, W) in [0, 1]) -> (B,)`` score, higher = better.

    ``weights``: a pyiqa MUSIQ checkpoint (.pth, read with ``weights_only=True``) or a .safetensors with
    the same keys; default: ``$D2TURB_MUSIQ_WEIGHTS`` (file or folder), else ``$D2TURB_CACHE_DIR/musiq/``
    (default ``~/.cache/d2turb/musiq/``). ``weights=False`` builds a randomly initialised model
    (tests / training); then ``config.num_classes`` defaults to 1.
    """

    def __init__(
        self,
        weights: str | os.PathLike | None | bool = None,
        device: str | torch.device = "cpu",
        config: MUSIQConfig | None = None,
        chunk_patches: int = 1024,
    ):
        super().__init__()
        config = config or MUSIQConfig()
        state, path = None, None
        if weights is not False:
            path = find_weights(weights)
            state = _load_state(path)
            config = replace(config, num_classes=config.num_classes or _num_classes(state, path))
        self.config = config = replace(config, num_classes=config.num_classes or 1)
        self.chunk_patches = chunk_patches
        w, p = config.stem_width, config.patch_size
        # with a checkpoint, the layers are built on the meta device (no memory, no random init) and take the
        # file's weights: one copy of the weights (~100 MB) in memory at a time instead of two
        with torch.device("meta") if state is not None else contextlib.nullcontext():
            self.conv_root = _StdConv(3, w, 7, stride=2, bias=False)
            self.gn_root = nn.GroupNorm(32, w, eps=1e-6)
            self.block1 = _Bottleneck(w, 4 * w)
            self.embedding = nn.Linear(4 * w * (p // 4) ** 2, config.hidden_size)
            self.transformer_encoder = _Encoder(config)
            linear = nn.Linear(config.hidden_size, config.num_classes)
        self.head = linear if config.num_classes == 1 else nn.Sequential(linear)  # keys head.* / head.0.*
        if state is not None:
            _load_strict(self, state, path)
        self.to(device).eval().requires_grad_(False)

    def _stem(self, patches: torch.Tensor) -> torch.Tensor:
        """(M, 3, P, P) -> (M, (P/4)^2 * 4w) tokens, flattened in TF's HWC order."""
        x = F.relu(self.gn_root(self.conv_root(patches)))
        (top, bottom), (left, right) = _same_padding(x.shape[2], 3, 2), _same_padding(x.shape[3], 3, 2)
        x = F.max_pool2d(F.pad(x, (left, right, top, bottom)), 3, 2)  # zero pad == -inf pad after ReLU
        return self.block1(x).permute(0, 2, 3, 1).reshape(x.shape[0], -1)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if isinstance(image, torch.Tensor) and image.ndim == 3:
            image = image[None]
        check_image_tensor(image, "MUSIQ input", channels=3)
        param = self.embedding.weight
        x = image.to(param.device, param.dtype) * 2 - 1
        patches, spatial, scale = multiscale_patches(x, self.config)
        b, n = patches.shape[:2]
        flat = patches.reshape(b * n, *patches.shape[2:])
        stem = torch.cat([self._stem(c) for c in flat.split(self.chunk_patches)])
        tokens = self.embedding(stem.reshape(b, n, -1))
        cls = self.transformer_encoder(tokens, spatial, scale)[:, 0]
        out = self.head(cls)
        if self.config.num_classes == 1:
            return out[:, 0]
        probs = out.softmax(-1)  # AVA: score = mean of the 1..10 distribution
        return probs @ torch.arange(1, probs.shape[-1] + 1, dtype=probs.dtype, device=probs.device)


def _load_strict(model: nn.Module, state: dict[str, torch.Tensor], path: Path) -> None:
    wanted = model.state_dict()
    missing = [k for k in wanted if k not in state]
    unexpected = [k for k in state if k not in wanted]
    if missing or unexpected:
        raise D2TurbError(
            f"{path} is not a MUSIQ checkpoint for this config: {len(missing)} missing keys "
            f"({', '.join(missing[:3])}), {len(unexpected)} unexpected ({', '.join(unexpected[:3])})"
        )
    bad = [k for k in wanted if state[k].shape != wanted[k].shape]
    if bad:
        k = bad[0]
        c = model.config
        raise D2TurbError(
            f"{path}: {len(bad)} MUSIQ weights have the wrong shape, e.g. {k} is {tuple(state[k].shape)} "
            f"in the file but {tuple(wanted[k].shape)} in the model (hidden {c.hidden_size}, "
            f"{c.num_layers} layers, mlp {c.mlp_dim}, stem {c.stem_width})"
        )
    if any(t.is_meta for t in wanted.values()):  # built on the meta device (MUSIQ.__init__)
        # each weight in a new tensor of the model's dtype, as load_state_dict would fill the model's own; the
        # file's tensor is dropped as soon as it is copied
        filled = {k: torch.empty(t.shape, dtype=t.dtype).copy_(state.pop(k)) for k, t in wanted.items()}
        model.load_state_dict(filled, assign=True)
    else:
        model.load_state_dict(state)


def find_weights(weights: str | os.PathLike | None = None) -> Path:
    """The MUSIQ checkpoint path: explicit argument, else $D2TURB_MUSIQ_WEIGHTS, else the cache folder."""
    if weights:
        path = Path(weights).expanduser()
        if not path.is_file():
            raise D2TurbError(
                f"MUSIQ weights file not found: {path} (pass an existing pyiqa musiq_*_ckpt-*.pth; "
                f"nothing is downloaded)"
            )
        return path
    folders = [cache_dir("musiq")]
    if os.environ.get(ENV_VAR):
        given = Path(os.environ[ENV_VAR]).expanduser()
        if given.is_file():
            return given
        if not given.is_dir():
            raise D2TurbError(f"{ENV_VAR}={given}: no such file or folder (point it at a MUSIQ checkpoint)")
        folders.insert(0, given)
    for folder in folders:
        candidates = [folder / n for n in FILE_NAMES] + sorted(folder.glob(FILE_GLOB))
        for path in candidates:
            if path.is_file():
                return path
    raise D2TurbError(
        f"MUSIQ weights not found: pass weights=FILE, set {ENV_VAR}=FILE, or put "
        f"musiq_koniq_ckpt-e95806b9.pth (IQA-PyTorch release) in {cache_dir('musiq')} (nothing is downloaded)"
    )


@lru_cache(maxsize=2)  # bounded: each model holds ~100 MB; the key's mtime drops a file replaced on disk
def _cached_model(path: str, mtime_ns: int, device: str) -> MUSIQ:
    return MUSIQ(Path(path), device=device)


def musiq(image: torch.Tensor, weights: str | os.PathLike | None = None, device: str = "cpu") -> torch.Tensor:
    """MUSIQ score of ``image`` (3, H, W) -> scalar tensor or (B, 3, H, W) -> (B,).

    The last two models used (per weights file and device) stay loaded.
    """
    path = find_weights(weights).resolve()
    model = _cached_model(str(path), path.stat().st_mtime_ns, str(device))
    with torch.no_grad():
        score = model(image)
    return score[0] if image.ndim == 3 else score
