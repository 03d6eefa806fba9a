"""d2turb.device: the device a name resolves to, and the distributed environment read in one place."""

import pytest
import torch

from d2turb.device import DistributedEnv, distributed_env, resolve_device
from d2turb.errors import D2TurbError


def test_resolve_device_rules(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu") and resolve_device(None).type in ("cpu", "cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == torch.device("cuda", 0)
    assert resolve_device("auto", local_rank=3) == torch.device("cuda", 1)  # ranks wrap onto the GPUs
    assert resolve_device("CUDA:1") == torch.device("cuda", 1)
    with pytest.raises(D2TurbError, match="2 GPU"):
        resolve_device("cuda:2")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(D2TurbError, match="CUDA is not available"):
        resolve_device("cuda:0")


def test_distributed_environment_is_read_in_one_place(monkeypatch):
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert distributed_env() == DistributedEnv(rank=0, world=1, local_rank=0)  # one process
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("RANK", "3")
    assert distributed_env() == DistributedEnv(3, 4, 3)  # LOCAL_RANK defaults to RANK (one machine)
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert distributed_env() == DistributedEnv(3, 4, 1)
    monkeypatch.setenv("LOCAL_RANK", "one")
    with pytest.raises(D2TurbError, match="LOCAL_RANK must be an integer, got 'one'"):
        distributed_env()
    monkeypatch.setenv("LOCAL_RANK", "0")
    monkeypatch.setenv("RANK", "4")
    with pytest.raises(D2TurbError, match="bad distributed environment: RANK=4 WORLD_SIZE=4"):
        distributed_env()
