"""d2turb.train: the multi-stage objective (Sec. 3.3), YAML configs and the (DDP) training loop."""

from d2turb.train.config import DEFAULTS, Config, load_config
from d2turb.train.distributed import init_distributed
from d2turb.train.ema import EMA
from d2turb.train.losses import (
    NATIVE_LOSS,
    NATIVE_LOSSES,
    MultiStageLoss,
    PerceptualLoss,
    build_loss,
    l1_loss,
    psnr_loss,
)
from d2turb.train.status import read_status
from d2turb.train.trainer import Trainer

__all__ = [
    "DEFAULTS",
    "Config",
    "EMA",
    "load_config",
    "MultiStageLoss",
    "PerceptualLoss",
    "build_loss",
    "l1_loss",
    "psnr_loss",
    "NATIVE_LOSS",
    "NATIVE_LOSSES",
    "Trainer",
    "init_distributed",
    "read_status",
]
