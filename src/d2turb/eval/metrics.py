"""Full-reference image metrics: functional ``psnr``/``ssim`` and torchmetrics-style accumulators.

Images are float tensors (B, C, H, W) (or one image (C, H, W)) in [0, 1]. :class:`KeyedMean` is the one running
mean of per-sample values (per key, overall and per group such as a turbulence bin) behind every average d2turb
reports; the accumulators ``PSNR``, ``SSIM`` and ``LPIPSMetric`` use it for one key. Under ``torch.distributed``
sums and counts are all-reduced in ``compute()``, so every rank gets the global mean.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence

import torch
import torch.distributed as dist
import torch.nn.functional as F

from d2turb.device import collective_device
from d2turb.errors import D2TurbError
from d2turb.eval.lpips import LPIPS
from d2turb.ops.checks import check_image_tensor

K1, K2 = 0.01, 0.03  # Wang et al. 2004 stabilising constants
MAX_PSNR_DB = 100.0  # identical images: PSNR is capped here instead of +inf, so means stay finite


def _pair(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    if pred.ndim == 3:
        pred = pred[None]
    if target.ndim == 3:
        target = target[None]
    check_image_tensor(pred, "pred")
    check_image_tensor(target, "target")
    if pred.shape != target.shape:
        raise D2TurbError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    return pred, target


def quantise_8bit(image: torch.Tensor) -> torch.Tensor:
    """What a user gets from the saved 8-bit PNG: ``image`` clamped to [0, 1] and rounded to multiples of 1/255 (the
    metrics of restored images are computed on that)."""
    return (image.clamp(0, 1) * 255.0).round() / 255.0


def psnr(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Per-image PSNR in dB, shape (B,) (capped at 100 dB for identical images)."""
    pred, target = _pair(pred, target)
    mse = (pred.double() - target.double()).pow(2).flatten(1).mean(1)
    floor = data_range**2 * 10 ** (-MAX_PSNR_DB / 10)
    return 10 * torch.log10(data_range**2 / mse.clamp_min(floor))


def end_point_error(flow_px: torch.Tensor, target_px: torch.Tensor | None = None) -> torch.Tensor:
    """Flow end-point error: the mean over pixels of ‖flow − target‖₂ in pixels (``target`` None: zero flow).

    Shape:
        flow_px, target_px: (..., 2, H, W) → (...): a scalar for one flow, (B,) for a batch.
    """
    diff = flow_px if target_px is None else flow_px - target_px
    return diff.pow(2).sum(-3).sqrt().flatten(-2).mean(-1)


def _gaussian_kernel1d(sigma: float, truncate: float = 3.5) -> torch.Tensor:
    """The 1-D kernel of ``scipy.ndimage.gaussian_filter`` (radius = int(truncate * sigma + 0.5))."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _filter_valid(x: torch.Tensor, k1d: torch.Tensor) -> torch.Tensor:
    """Separable depthwise filtering without padding (the 'valid' part skimage keeps after cropping)."""
    c = x.shape[1]
    k = k1d.to(x)
    x = F.conv2d(x, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(x, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    data_range: float = 1.0,
    gaussian: bool = True,
    sigma: float = 1.5,
    win_size: int = 7,
) -> torch.Tensor:
    """Per-image mean SSIM (Wang et al. 2004), shape (B,), averaged over channels and pixels.

    ``gaussian=True`` (default) equals ``skimage.metrics.structural_similarity(..., channel_axis=-1,
    data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``;
    ``gaussian=False`` equals skimage's default (``win_size``x``win_size`` uniform window, sample covariance).
    Like skimage, the mean is taken over pixels whose window lies inside the image.
    """
    pred, target = _pair(pred, target)
    x, y = pred, target  # float32 in, float32 filtering (fast, ~1e-6 from float64); float64 in, float64
    if gaussian:
        k1d, cov_norm = _gaussian_kernel1d(sigma), 1.0
    else:
        if win_size < 3 or win_size % 2 == 0:
            raise D2TurbError(f"ssim: win_size must be odd and >= 3, got {win_size}")
        k1d = torch.full((win_size,), 1.0 / win_size, dtype=torch.float64)
        cov_norm = win_size**2 / (win_size**2 - 1)  # sample covariance
    if min(x.shape[-2:]) < len(k1d):
        raise D2TurbError(f"ssim: images of {x.shape[-1]}x{x.shape[-2]} are smaller than the {len(k1d)}-pixel window")
    stats = _filter_valid(torch.cat([x, y, x * x, y * y, x * y], dim=1), k1d).chunk(5, dim=1)
    mx, my, mxx, myy, mxy = stats
    vx, vy, cxy = cov_norm * (mxx - mx * mx), cov_norm * (myy - my * my), cov_norm * (mxy - mx * my)
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))  # Eq. (13) of Wang et al.
    return s.flatten(1).double().mean(1)


class KeyedMean:
    """Running means of per-sample values by key, over all samples and per group (e.g. per turbulence bin).

    Like torchmetrics' ``MeanMetric`` for several keys at once, split by group like its ``ClasswiseWrapper``:
    :meth:`update` adds a batch of per-sample values for each key, with the group of each sample; :meth:`compute`
    gives the means; :meth:`reset` starts again. Sums and counts are float64, summed in the order they come.

    Args:
        sync_on_compute: when ``torch.distributed`` is initialised with more than one process, all-reduce sums and
            counts in the first :meth:`compute` after an update (a collective: every rank calls it), so that every
            rank gets the means over all ranks' samples, whichever keys and groups each rank saw. False for a
            process that evaluates everything alone.

    Example:
        >>> mean = KeyedMean()
        >>> mean.update({"psnr": torch.tensor([30.0, 20.0, 40.0])}, groups=["weak", "strong", "weak"])
        >>> mean.compute(), mean.compute("weak"), mean.count("psnr", "strong")
        ({'psnr': 30.0}, {'psnr': 35.0}, 1)
    """

    def __init__(self, sync_on_compute: bool = True) -> None:
        self.sync_on_compute = sync_on_compute
        self._sums: dict[tuple[Hashable, Hashable], list[float]] = {}  # (key, group or None) → [sum, count]
        self._reduced: dict[tuple[Hashable, Hashable], list[float]] | None = None

    def reset(self) -> None:
        """Forget every value seen."""
        self._sums, self._reduced = {}, None

    @torch.no_grad()
    def update(
        self,
        values: Mapping[Hashable, torch.Tensor | float | Sequence[float]],
        groups: torch.Tensor | Sequence[Hashable] | Hashable | None = None,
    ) -> None:
        """Add per-sample values.

        Args:
            values: key → the batch's per-sample values (a float is one sample).
            groups: None; one group label (a str or an int, not None) for the whole batch; or one label per sample
                (a tensor, list or tuple). Each value also counts towards the mean of its group.

        Shape:
            values[key]: (N,) (any shape is flattened); groups per sample: (N,).

        Raises:
            D2TurbError: per-sample groups whose number is not N.
        """
        per_sample = isinstance(groups, (list, tuple)) or (isinstance(groups, torch.Tensor) and groups.ndim > 0)
        masks = {}  # label → which samples carry it
        if per_sample:
            labels = groups.reshape(-1).tolist() if isinstance(groups, torch.Tensor) else list(groups)
            masks = {label: torch.tensor([x == label for x in labels]) for label in dict.fromkeys(labels)}
        elif isinstance(groups, torch.Tensor):
            groups = groups.item()
        for key, batch in values.items():
            batch = batch.detach() if isinstance(batch, torch.Tensor) else torch.as_tensor(batch, dtype=torch.float64)
            batch = batch.reshape(-1).double().cpu()
            if per_sample and len(labels) != batch.numel():
                raise D2TurbError(f"KeyedMean: {len(labels)} group labels for {batch.numel()} values of {key!r}")
            self._add(key, None, batch)
            if per_sample:
                for label, mask in masks.items():
                    self._add(key, label, batch[mask])
            elif groups is not None:
                self._add(key, groups, batch)
        self._reduced = None

    def _add(self, key: Hashable, group: Hashable, batch: torch.Tensor) -> None:
        entry = self._sums.setdefault((key, group), [0.0, 0])
        entry[0] += float(batch.sum())
        entry[1] += batch.numel()

    def sync(self) -> None:
        """All-reduce sums and counts over the ``torch.distributed`` processes (a collective: every rank calls it);
        the means of :meth:`compute` are then global until the next :meth:`update` or :meth:`reset`. One process,
        or torch.distributed not initialised: the local sums."""
        entries = list(self._sums)
        table = [self._sums[e] for e in entries]
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            seen: list = [None] * dist.get_world_size()
            dist.all_gather_object(seen, entries)
            entries = list(dict.fromkeys(e for rank_entries in seen for e in rank_entries))  # the same on every rank
            sums = torch.tensor([self._sums.get(e, [0.0, 0]) for e in entries], dtype=torch.float64).reshape(-1, 2)
            sums = sums.to(collective_device())
            dist.all_reduce(sums, op=dist.ReduceOp.SUM)
            table = sums.cpu().tolist()
        self._reduced = {e: [float(s), float(n)] for e, (s, n) in zip(entries, table)}

    def _table(self) -> dict[tuple[Hashable, Hashable], list[float]]:
        if not self.sync_on_compute:
            return self._sums
        if self._reduced is None:
            self.sync()
        return self._reduced

    def compute(self, group: Hashable = None) -> dict[Hashable, float]:
        """Mean per key over all samples (``group`` None) or over the samples of ``group``.

        Returns:
            key → mean, in the order keys were first seen; keys without samples (in ``group``) are left out.
        """
        return {key: s / n for (key, g), (s, n) in self._table().items() if g == group and n > 0}

    def count(self, key: Hashable, group: Hashable = None) -> int:
        """How many samples the mean of ``key`` (in ``group``) is over."""
        return int(self._table().get((key, group), (0.0, 0))[1])

    def groups(self) -> list[Hashable]:
        """The group labels seen, in the order they were first seen."""
        return list(dict.fromkeys(g for _, g in self._table() if g is not None))


class MeanMetric:
    """Running mean of per-image values (a :class:`KeyedMean` of one key); DDP-safe (sums and counts are
    all-reduced in ``compute``)."""

    def __init__(self) -> None:
        self._mean = KeyedMean()

    def reset(self) -> None:
        self._mean.reset()

    def per_image(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    @torch.no_grad()
    def update(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Add a batch; returns its per-image values."""
        values = self.per_image(pred, target).detach().double().cpu()
        self._mean.update({"mean": values})
        return values

    def compute(self) -> float:
        """Mean over every image seen (on all ranks when torch.distributed is initialised)."""
        return self._mean.compute().get("mean", math.nan)


class PSNR(MeanMetric):
    def __init__(self, data_range: float = 1.0) -> None:
        self.data_range = data_range
        super().__init__()

    def per_image(self, pred, target):
        return psnr(pred, target, self.data_range)


class SSIM(MeanMetric):
    def __init__(self, data_range: float = 1.0, gaussian: bool = True, sigma: float = 1.5, win_size: int = 7) -> None:
        self.kwargs = dict(data_range=data_range, gaussian=gaussian, sigma=sigma, win_size=win_size)
        super().__init__()

    def per_image(self, pred, target):
        return ssim(pred, target, **self.kwargs)


class LPIPSMetric(MeanMetric):
    """Mean LPIPS; ``model`` is a ``d2turb.eval.lpips.LPIPS`` (or built from its keyword arguments)."""

    def __init__(self, model=None, **lpips_kwargs) -> None:
        if model is None:
            model = LPIPS(**lpips_kwargs)
        self.model = model.eval()
        super().__init__()

    def per_image(self, pred, target):
        pred, target = _pair(pred, target)
        device = next(self.model.parameters()).device
        return self.model(pred.to(device), target.to(device))
