"""Channel ("transposed") attention of Restormer's MDTA and the cosine ASPI variant against a reference written
from the definition (Zamir et al. 2022, Eq. 2): per head, q and k are L2-normalised over the pixels, so each
logit is the cosine similarity of two channels' feature maps times a learned temperature."""

import pytest
import torch

from d2turb.models.common import transposed_attention


def _reference(q, k, v, heads, temperature):
    """Loops over batch, head and channel pairs in float64: logit(i, j) = τ_h·<q_i, k_j>/(|q_i| |k_j|), the dot
    products and norms over the H·W pixels of channel i of q and channel j of k; out_i = Σ_j softmax_j · v_j."""
    b, c, h, w = q.shape
    d = c // heads
    q, k, v = (t.double().reshape(b, c, h * w) for t in (q, k, v))
    out = torch.zeros(b, c, h * w, dtype=torch.float64)
    for n in range(b):
        for head in range(heads):
            rows = range(head * d, (head + 1) * d)
            logits = torch.tensor(
                [
                    [
                        float(temperature[head]) * float(q[n, i] @ k[n, j] / (q[n, i].norm() * k[n, j].norm()))
                        for j in rows
                    ]
                    for i in rows
                ],
                dtype=torch.float64,
            )
            weights = logits.exp() / logits.exp().sum(1, keepdim=True)
            for a, i in enumerate(rows):
                out[n, i] = sum(weights[a, c2] * v[n, j] for c2, j in enumerate(rows))
    return out.reshape(b, c, h, w)


@pytest.mark.parametrize("heads", [1, 2])
def test_transposed_attention_matches_the_cosine_definition(heads):
    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(2, 4, 5, 6, generator=g) for _ in range(3))
    temperature = torch.tensor([1.7, 0.6][:heads]).view(heads, 1, 1)
    out, attn = transposed_attention(q, k, v, heads, temperature, return_attn=True)
    torch.testing.assert_close(out.double(), _reference(q, k, v, heads, temperature), atol=1e-5, rtol=1e-5)
    assert attn.shape == (2, heads, 4 // heads, 4 // heads)
    torch.testing.assert_close(attn.sum(-1), torch.ones(2, heads, 4 // heads))


def test_scaling_one_channel_of_q_or_k_changes_nothing():
    """Normalised over pixels, a channel's overall gain cancels: the logits are cosines, bounded by τ."""
    g = torch.Generator().manual_seed(1)
    q, k, v = (torch.randn(1, 4, 3, 7, generator=g) for _ in range(3))
    temperature = torch.ones(1, 1, 1)
    base = transposed_attention(q, k, v, 1, temperature)
    gain = torch.tensor([5.0, 1.0, 0.2, 3.0]).view(1, 4, 1, 1)
    torch.testing.assert_close(transposed_attention(q * gain, k, v, 1, temperature), base)
    torch.testing.assert_close(transposed_attention(q, k * gain, v, 1, temperature), base)
