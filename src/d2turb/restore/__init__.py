"""d2turb.restore: remove turbulence. Single images of any size with a trained model (:class:`Restorer`, tiled);
clips by registration across frames, fusion and deblurring (:func:`restore_clip`, ``d2turb.clip``)."""

from d2turb.models.hub import IDENTITY_NAME, resolve_weights, weights_search_path
from d2turb.models.weights import WEIGHTS_SUFFIX
from d2turb.restore.single import (
    IdentityRestorer,
    Restorer,
    axis_window,
    load_restoration_model,
    tile_starts,
    warp_in_strips,
)

__all__ = [
    "Restorer",
    "IdentityRestorer",
    "load_restoration_model",
    "resolve_weights",
    "weights_search_path",
    "IDENTITY_NAME",
    "WEIGHTS_SUFFIX",
    "tile_starts",
    "axis_window",
    "warp_in_strips",
]
