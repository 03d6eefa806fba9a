"""The fixed split of the clean image folders, by folder name (the model card states it).

* test: ``bsd100``, ``sunhays_outdoor`` — never seen in training or model selection;
* validation: ``set14``, ``mcmaster`` — model selection;
* train: every other folder (at the time of writing ``urban100``, ``bsds500``, ``camvid``, ``strecha_mvs``,
  ``sfm_landmarks``, ``t91`` of ``../shared/data/clean``).
"""

from __future__ import annotations

import os
from pathlib import Path

TEST_FOLDERS: tuple[str, ...] = ("bsd100", "sunhays_outdoor")
VAL_FOLDERS: tuple[str, ...] = ("set14", "mcmaster")
SPLITS: tuple[str, ...] = ("train", "val", "test")


def split_of(folder: str | os.PathLike) -> str:
    """The split (``train`` | ``val`` | ``test``) of a clean-image folder, from its name alone.

    Args:
        folder: a folder path or name; only its last component counts.

    Returns:
        ``"test"`` for :data:`TEST_FOLDERS`, ``"val"`` for :data:`VAL_FOLDERS`, else ``"train"``.
    """
    name = Path(folder).name
    if name in TEST_FOLDERS:
        return "test"
    if name in VAL_FOLDERS:
        return "val"
    return "train"
