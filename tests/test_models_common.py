"""ChannelLayerNorm against the LayerNorm formula evaluated independently in float64 (numpy / elementwise torch)."""

import numpy as np
import pytest
import torch

from d2turb.models.common import ChannelLayerNorm


def _reference(x: np.ndarray, w: np.ndarray, b: np.ndarray | None, eps: float) -> np.ndarray:
    """(x − mean_c)/√(var_c + ε)·w + b over the channel axis of (B, C, H, W); BiasFree: x/√(var_c + ε)·w."""
    mean = x.mean(axis=1, keepdims=True)
    var = ((x - mean) ** 2).mean(axis=1, keepdims=True)
    if b is None:
        return x / np.sqrt(var + eps) * w[None, :, None, None]
    return (x - mean) / np.sqrt(var + eps) * w[None, :, None, None] + b[None, :, None, None]


@pytest.mark.parametrize("bias", [True, False])
def test_channel_layer_norm_matches_the_formula(bias):
    g = torch.Generator().manual_seed(0)
    norm = ChannelLayerNorm(6, bias=bias, eps=1e-5)
    with torch.no_grad():
        norm.weight.copy_(torch.randn(6, generator=g))
        if bias:
            norm.bias.copy_(torch.randn(6, generator=g))
    x = torch.randn(2, 6, 5, 7, generator=g) * 3 + 1.5  # a mean offset: the bias-free variant must keep it
    y = norm(x)
    b = norm.bias.detach().double().numpy() if bias else None
    ref = _reference(x.double().numpy(), norm.weight.detach().double().numpy(), b, 1e-5)
    assert y.shape == x.shape and y.dtype == torch.float32
    np.testing.assert_allclose(y.detach().numpy(), ref, rtol=0, atol=1e-5)  # float32 rounding of O(1) values


def test_channel_layer_norm_gradients_match_float64_formula():
    g = torch.Generator().manual_seed(1)
    norm = ChannelLayerNorm(4)
    with torch.no_grad():
        norm.weight.copy_(torch.randn(4, generator=g))
        norm.bias.copy_(torch.randn(4, generator=g))
    x = torch.randn(1, 4, 3, 5, generator=g)
    probe = torch.randn(1, 4, 3, 5, generator=g)
    x32 = x.clone().requires_grad_(True)
    (norm(x32) * probe).sum().backward()
    x64 = x.double().requires_grad_(True)
    w64 = norm.weight.detach().double().requires_grad_(True)
    mean = x64.mean(1, keepdim=True)
    ref = (x64 - mean) / ((x64 - mean).pow(2).mean(1, keepdim=True) + 1e-5).sqrt() * w64[:, None, None]
    (ref * probe.double()).sum().backward()
    torch.testing.assert_close(x32.grad.double(), x64.grad, rtol=0, atol=1e-5)
    torch.testing.assert_close(norm.weight.grad.double(), w64.grad, rtol=0, atol=1e-5)


@pytest.mark.parametrize("bias", [True, False])
def test_channel_layer_norm_in_bfloat16_input_and_module(bias):
    x = torch.randn(2, 8, 9, 11) * 2 + 1
    ref = ChannelLayerNorm(8, bias=bias)(x)
    for norm in (ChannelLayerNorm(8, bias=bias), ChannelLayerNorm(8, bias=bias).bfloat16()):
        y = norm(x.bfloat16())
        assert y.dtype == torch.bfloat16
        assert (y.float() - ref).abs().max() < 0.1  # bf16 input rounding (2^-8 relative) of |x| up to ~10


def test_channel_layer_norm_feeds_a_convolution():
    norm, conv = ChannelLayerNorm(8), torch.nn.Conv2d(8, 8, 3, padding=1)
    x = torch.randn(2, 8, 9, 11)
    y = norm(x)
    torch.testing.assert_close(conv(y), conv(y.contiguous()), rtol=1e-5, atol=1e-5)  # channels-last layout is fine
