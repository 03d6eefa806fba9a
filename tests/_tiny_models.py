"""The tests' tiny models: one builder per kind, so that the tests that need a small random model of that kind
build the same one (seeded, in this process's torch RNG)."""

import torch

TINY_NAFNET = {"width": 8, "enc_blocks": [1], "dec_blocks": [1]}  # a one-level NAFNet: create_model("nafnet", **…)
# the tiny D²Turb: a NAFNet backbone and a U-Net rectifier of width 8, the rectifier's cosine ASPI
TINY_D2TURB = {
    "backbone": "nafnet",
    "injection": "aspi_cosine",
    "rectifier": "unet",
    "backbone_cfg": {"width": 8, "enc_blocks": [1, 1], "dec_blocks": [1, 1]},
    "rectifier_cfg": {"width": 8, "mults": [1, 1, 2, 2], "depth": 3},
}


def tiny_d2turb(flow_std: float, seed: int = 0) -> torch.nn.Module:
    """A tiny random D²Turb (``TINY_D2TURB``) built after ``torch.manual_seed(seed)``, its flow head (zero at
    initialisation: an identity warp) drawn normal with std ``flow_std`` so that the warp matters; in train mode.

    Args:
        flow_std: std of the flow head's weights (2: |V̂| of a few px on natural images).
        seed: the global torch seed set before the model is built.
    Returns:
        The model (its next random draws continue the same seeded stream).
    """
    from d2turb.models import create_model

    torch.manual_seed(seed)
    cfg = {k: dict(v) if isinstance(v, dict) else v for k, v in TINY_D2TURB.items()}
    model = create_model("d2turb", **cfg)
    torch.nn.init.normal_(model.rectifier.flow_head.weight, std=flow_std)
    return model
