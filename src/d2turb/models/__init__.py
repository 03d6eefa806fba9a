"""d2turb.models: the D²Turb model family (backbones, tilt rectifier, injection variants), registry and weights I/O.

To add a backbone, create ``d2turb/models/<name>.py`` with a class decorated by ``@register_backbone("<name>")`` and
add it to the imports below (see docs/models.md)."""

# register the backbones and models: D²Turb's own, then the paper's comparison methods (docs/models.md, "Baselines")
from d2turb.models import adair, atnet, focalnet, nafnet, restormer, tmt, turbnet  # noqa: F401
from d2turb.models.complexity import (
    count_flops,
    count_parameters,
    flop_counts,
    measure_latency,
    model_cost,
    parameter_count,
)
from d2turb.models.d2turb import BackboneRestorer, D2Turb
from d2turb.models.injection import ASPI, CosineASPI
from d2turb.models.output import ModelOutput, model_output
from d2turb.models.rectifier import TiltRectifier, UNetRectifier
from d2turb.models.registry import (
    create_backbone,
    create_model,
    list_backbones,
    list_models,
    register_backbone,
    register_model,
)
from d2turb.models.weights import load_pretrained, save_pretrained

__all__ = [
    "ModelOutput",
    "model_output",
    "create_model",
    "create_backbone",
    "list_models",
    "list_backbones",
    "register_model",
    "register_backbone",
    "D2Turb",
    "BackboneRestorer",
    "TiltRectifier",
    "UNetRectifier",
    "ASPI",
    "CosineASPI",
    "save_pretrained",
    "load_pretrained",
    "count_parameters",
    "parameter_count",
    "count_flops",
    "flop_counts",
    "model_cost",
    "measure_latency",
]
