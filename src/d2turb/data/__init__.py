"""d2turb.data: paired-dataset generation (make-dataset), verification (check-dataset), PyTorch datasets."""

from d2turb.data.check import CheckReport, check_dataset
from d2turb.data.config import DatasetConfig
from d2turb.data.datasets import CleanCropDataset, OnTheFlySynthesis, PairDataset, crop_sample, flip_sample
from d2turb.data.generate import generate_dataset
from d2turb.data.plan import plan_sample
from d2turb.data.sequence import SequenceDataset

__all__ = [
    "CheckReport",
    "CleanCropDataset",
    "DatasetConfig",
    "OnTheFlySynthesis",
    "PairDataset",
    "SequenceDataset",
    "check_dataset",
    "crop_sample",
    "flip_sample",
    "generate_dataset",
    "plan_sample",
]
