"""The app's work in plain Python (no gradio), as one namespace for the page (:mod:`d2turb.app.ui`), the
``d2turb app`` command and scripts. It lives in modules by concern:

* :mod:`d2turb.app.forms`: the page's controls as checked values (limits, Simulate settings → SI units, samples,
  the weights list);
* :mod:`d2turb.app.jobs`: one argument list per job, run as the command (``python -m d2turb ARGV`` in the run
  folder) and shown as ``d2turb ARGV``: the page holds no second copy of the command line;
* :mod:`d2turb.app.tabs`: what each button does (``run_simulation``, ``run_restore``, ``run_clip``);
* :mod:`d2turb.app.views`: the pictures and tables the page shows;
* :mod:`d2turb.app.workspace`: the temp folder and the download bundles.

Every problem a user can cause raises :class:`d2turb.errors.D2TurbError` with a one-line message; the UI layer
turns it into a message in the page.
"""

from __future__ import annotations

from d2turb.app.forms import (
    DEPTH_SOURCES,
    IMAGE_SOURCES,
    STRENGTHS,
    Limits,
    SimSettings,
    SimValues,
    check_pixels,
    default_weights,
    fmt_float,
    parse_wavelengths_nm,
    safe_stem,
    sample_image,
    sim_values,
    weights_choices,
)
from d2turb.app.jobs import (
    CLIP_SIM_FRAMES,
    clip_argv,
    clip_simulate_argv,
    command_text,
    restore_argv,
    run_command,
    simulate_argv,
    write_command,
)
from d2turb.app.tabs import ClipOutput, RestoreOutput, SimOutput, run_clip, run_restore, run_simulation
from d2turb.app.views import (
    NIQE_CAVEAT,
    PREVIEW_SIDE,
    derived_markdown,
    flow_view,
    niqe_markdown,
    preview,
)
from d2turb.app.workspace import Workspace, bundle, prepare_environment
from d2turb.data.samples import SAMPLES
from d2turb.io import IMAGE_SUFFIXES
from d2turb.models.hub import shipped_weights_dir

__all__ = [
    "CLIP_SIM_FRAMES",
    "DEPTH_SOURCES",
    "IMAGE_SOURCES",
    "IMAGE_SUFFIXES",
    "NIQE_CAVEAT",
    "PREVIEW_SIDE",
    "SAMPLES",
    "STRENGTHS",
    "ClipOutput",
    "Limits",
    "RestoreOutput",
    "SimOutput",
    "SimSettings",
    "SimValues",
    "Workspace",
    "bundle",
    "check_pixels",
    "clip_argv",
    "clip_simulate_argv",
    "command_text",
    "default_weights",
    "derived_markdown",
    "flow_view",
    "fmt_float",
    "niqe_markdown",
    "parse_wavelengths_nm",
    "prepare_environment",
    "preview",
    "restore_argv",
    "run_clip",
    "run_command",
    "run_restore",
    "run_simulation",
    "safe_stem",
    "sample_image",
    "shipped_weights_dir",
    "sim_values",
    "simulate_argv",
    "weights_choices",
    "write_command",
]
