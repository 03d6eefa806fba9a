"""The authors' D²Turb checkpoints (HertzDot222/D2Turb) in our names, and files of d2turb before format 2 with the
defaults of their time: :func:`convert_official_state_dict` renames the authors' keys (:func:`official_key` names ours
the authors' way, for messages), :func:`legacy_config` spells out a format-1 file's old defaults."""

from __future__ import annotations

import torch

# The authors' key names (left) → ours (right). Prefix rules, first match wins; the block rules apply to backbone keys.
_OFFICIAL_PREFIXES = [
    ("restormer.embed_conv.", "backbone.patch_embed."),
    ("restormer.encoders.0.", "backbone.encoder_level1."),
    ("restormer.encoders.1.", "backbone.encoder_level2."),
    ("restormer.encoders.2.", "backbone.encoder_level3."),
    ("restormer.encoders.3.", "backbone.latent."),
    ("restormer.downs.0.body.", "backbone.down1_2."),
    ("restormer.downs.1.body.", "backbone.down2_3."),
    ("restormer.downs.2.body.", "backbone.down3_4."),
    ("restormer.ups.0.body.", "backbone.up4_3."),
    ("restormer.ups.1.body.", "backbone.up3_2."),
    ("restormer.ups.2.body.", "backbone.up2_1."),
    ("restormer.reduces.0.", "backbone.reduce_chan_level3."),
    ("restormer.reduces.1.", "backbone.reduce_chan_level2."),
    ("restormer.decoders.0.", "backbone.decoder_level3."),
    ("restormer.decoders.1.", "backbone.decoder_level2."),
    ("restormer.decoders.2.", "backbone.decoder_level1."),
    ("restormer.", "backbone."),
    ("rectifier.aspi.", "rectifier.inject."),
]


_OFFICIAL_BLOCK = [
    (".attention.qkv_conv.", ".attn.qkv_dwconv."),
    (".attention.", ".attn."),
    (".feed_forward.conv.", ".ffn.dwconv."),
    (".feed_forward.", ".ffn."),
]


def _rename(key: str, prefixes, block) -> str:
    for old, new in prefixes:
        if key.startswith(old):
            key = new + key[len(old) :]
            if new.startswith(("backbone.", "restormer.")):
                for b_old, b_new in block:
                    key = key.replace(b_old, b_new)
            return key
    return key


def official_key(key: str) -> str:
    """Our key → the authors' name for it (for messages)."""
    return _rename(key, [(n, o) for o, n in _OFFICIAL_PREFIXES], [(n, o) for o, n in _OFFICIAL_BLOCK])


def is_official_layout(state_dict: dict) -> bool:
    return any(k.startswith(("restormer.", "rectifier.aspi.")) for k in state_dict)


def convert_official_state_dict(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename the authors' D²Turb keys to ours (``restormer.*`` → ``backbone.*``, ``rectifier.aspi.*`` →
    ``rectifier.inject.*``; the rectifier's other keys are the same) and reshape the Restormer temperatures
    (1, heads, 1, 1) → (heads, 1, 1). Keys already in our layout pass through unchanged."""
    out = {}
    for key, value in state_dict.items():
        new = _rename(key, _OFFICIAL_PREFIXES, _OFFICIAL_BLOCK)
        if key.startswith("restormer.") and new.endswith(".attn.temperature") and value.ndim == 4:
            value = value.reshape(value.shape[1:])
        out[new] = value
    return out


def legacy_config(name: str, config: dict) -> dict:
    """The config of a file written before format 2 with its defaults spelled out: then Restormer's LayerNorm was
    bias-free, ``d2turb`` (and its presets) used the U-Net rectifier and ``injection="aspi"`` meant the cosine
    variant."""
    cfg = dict(config)
    backbones = {"d2turb": "restormer", "d2turb_lite": "nafnet", "d2turb_focalnet": "focalnet", "d2turb_adair": "adair"}
    if name == "restormer":
        cfg.setdefault("norm_bias", False)
    elif name in backbones:
        if cfg.get("backbone", backbones[name]) == "restormer":
            cfg["backbone_cfg"] = {"norm_bias": False, **(cfg.get("backbone_cfg") or {})}
        cfg.setdefault("rectifier", "unet")
        if cfg.get("injection", "aspi") == "aspi":
            cfg["injection"] = "aspi_cosine"
    return cfg
