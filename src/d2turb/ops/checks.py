"""Checks of tensor arguments, each failure a one-line :class:`~d2turb.errors.D2TurbError` naming the argument."""

from __future__ import annotations

import torch

from d2turb.errors import D2TurbError


def check_shape(x, shape: str, name: str = "input", floating: bool = False) -> None:
    """Refuse ``x`` unless it is a tensor of the shape ``shape`` (kornia's ``KORNIA_CHECK_SHAPE``, in one line).

    Args:
        x: the argument to check.
        shape: its dimensions separated by spaces: a name (``B``, ``C``, ``H``…) matches any size, an integer only
            that size, and leading ones in brackets may be absent; e.g. ``"B C H W"``, ``"B 2 H W"``, ``"B 1 40 56"``,
            ``"[B] 3 H W"`` (an image or a batch of them).
        name: the argument's name in the message.
        floating: also require a floating dtype.

    Raises:
        D2TurbError: ``"{name} must have shape (B, 2, H, W), got (1, 3, 8, 8)"`` for a wrong rank or size (``must be
            a tensor of shape …`` for a non-tensor, ``must be a floating tensor`` for an integer one).
    """
    dims = shape.split()
    wanted = f"({', '.join(dims)})"
    if not isinstance(x, torch.Tensor):
        raise D2TurbError(f"{name} must be a tensor of shape {wanted}, got {type(x).__name__}")
    optional = next((i for i, d in enumerate(dims) if not d.startswith("[")), len(dims))
    sizes = [d.strip("[]") for d in dims]
    if not len(dims) - optional <= x.ndim <= len(dims) or any(
        d.isdigit() and int(d) != n for d, n in zip(sizes[len(dims) - x.ndim :], x.shape)
    ):
        raise D2TurbError(f"{name} must have shape {wanted}, got {tuple(x.shape)}")
    if floating:
        _check_floating(x, name)


def _check_floating(x: torch.Tensor, name: str) -> None:
    if not x.is_floating_point():
        raise D2TurbError(f"{name} must be a floating tensor, got {x.dtype}")


def check_image_tensor(x: torch.Tensor, name: str = "image", channels: int | None = None) -> None:
    """Refuse ``x`` unless it is a floating (B, C, H, W) tensor (with ``channels`` channels) without NaN/inf."""
    check_shape(x, "B C H W", name)
    if channels is not None and x.shape[1] != channels:
        raise D2TurbError(f"{name}: expected {channels} channels, got {x.shape[1]}")
    _check_floating(x, name)
    if not torch.isfinite(x).all():
        raise D2TurbError(f"{name}: contains NaN or infinite values")
