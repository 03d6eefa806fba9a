"""The page of ``d2turb app`` (Gradio Blocks) and the server. The callbacks are thin: they call
:mod:`d2turb.app.core` (which runs each job as its ``d2turb`` command, :mod:`d2turb.app.jobs`) and turn its
one-line errors into ``gr.Error`` messages in the page.

Import this module only after :func:`d2turb.app.core.prepare_environment` when nothing may be written outside the
app's temp folder: gradio reads ``GRADIO_TEMP_DIR`` when it is imported.
"""

from __future__ import annotations

import functools
import html
import inspect
import logging
import re
from pathlib import Path
from types import SimpleNamespace

import gradio as gr

from d2turb.app import core
from d2turb.defaults import DEFAULT_DR0, DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX, MEASURED_TEMPORAL
from d2turb.errors import D2TurbError
from d2turb.eval.labels import GENERIC_STEMS, weights_label
from d2turb.io import image_size, read_image, write_image
from d2turb.sim import MODULATIONS
from d2turb.sim.params import BINS_RULE
from d2turb.video import VIDEO_SUFFIXES

SIM_DEFAULTS = core.SimSettings()  # the optics' defaults (d2turb.defaults) shown in the Simulate tab

log = logging.getLogger("d2turb.app")

INTRO = """# d2turb — depth-aware atmospheric turbulence
**Simulate** turns the physical knobs of the simulator (D/r0 or Cn², aperture, wavelength, range, pixel size, depth)
and shows what they do; **Restore** runs a trained model on your image or short video. Every result comes with the
`d2turb` command line that reproduces it. Everything stays on this machine."""

MAX_UPLOAD = "300mb"


def _error(message: str) -> gr.Error:
    text = html.escape(message, quote=False)  # gr.Error renders HTML
    try:
        return gr.Error(text, print_exception=False)
    except TypeError:  # a gradio release without print_exception
        return gr.Error(text)


def page_errors(workspace: core.Workspace):
    """Decorator: D2TurbError → gr.Error with its one line (temp-folder paths shortened); anything unexpected →
    one line naming the exception, the traceback only in the server log."""

    def deco(fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except gr.Error:
                raise
            except D2TurbError as exc:
                raise _error(_short(str(exc), workspace)) from None
            except Exception as exc:  # noqa: BLE001 - the page shows one line, the log keeps the traceback
                log.exception("d2turb app: unexpected error")
                what = f"{type(exc).__name__}: {_short(str(exc), workspace)}"
                raise _error(f"unexpected error ({what}); see the server log") from None

        return wrapper

    return deco


def _short(message: str, workspace: core.Workspace) -> str:
    """First line of ``message`` with paths inside the temp folder cut to their file name."""
    text = re.sub(re.escape(str(workspace.root)) + r"/(?:[^\s/]+/)*", "", message)
    return text.splitlines()[0] if text else text


def _weights_label(name: str, path: Path | None) -> str:
    if path is None:
        return f"{name}  (identity: output = input)"
    if path.stem.lower() in GENERIC_STEMS:  # a run folder's model.safetensors: its config's model and folder
        name = weights_label(path)
    return f"{name}  ({'shipped' if path.parent == core.shipped_weights_dir() else path.parent})"


def build_app(workspace: core.Workspace, limits: core.Limits | None = None) -> gr.Blocks:
    """The Blocks page: Simulate, Restore and Clip tabs. API names: ``/simulate``, ``/restore``, ``/clip``."""
    limits = limits or core.Limits()
    guard = page_errors(workspace)

    @guard
    def show_input(path):
        if not path:
            return None

        p = Path(path)
        w, h = image_size(p)
        core.check_pixels(p.name, w, h, max(limits.sim_pixels, limits.restore_pixels))
        return core.preview(read_image(p), workspace.new_run("preview") / "input.png")

    with gr.Blocks(title="d2turb", **_blocks_kwargs()) as demo:
        gr.Markdown(INTRO)
        with gr.Tab("Simulate", id="simulate"):
            _simulate_tab(demo, workspace, limits, guard, show_input)
        with gr.Tab("Restore", id="restore"):
            _restore_tab(workspace, limits, guard, show_input)
        with gr.Tab("Clip", id="clip"):
            _clip_tab(workspace, limits, guard)
    return demo


def _simulate_callback(workspace: core.Workspace, limits: core.Limits, guard):
    """The Simulate button: the page's fields → :func:`d2turb.app.core.run_simulation` → the result's views."""

    @guard
    def simulate(
        source,
        sample,
        upload,
        strength,
        dr0,
        cn2,
        aperture,
        wavelength,
        path_length,
        ifov,
        depth,
        depth_upload,
        disparity,
        modulation,
        offset,
        seed,
    ):
        settings = core.SimSettings(
            source=source,
            sample=sample,
            upload=upload,
            strength=strength,
            dr0=dr0,
            cn2=cn2,
            aperture_m=aperture,
            wavelength_nm=wavelength,
            path_length_m=path_length,
            ifov_urad=ifov,
            depth=depth,
            depth_upload=depth_upload,
            disparity=bool(disparity),
            modulation=modulation,
            offset_s=offset,
            seed=0 if seed is None else seed,
        )
        r = core.run_simulation(settings, workspace, limits)
        for w in r.warnings:
            gr.Warning(w)
        return (
            str(r.turb),
            str(r.tilt),
            str(r.flow),
            None if r.depth is None else str(r.depth),
            str(r.modulation),
            core.derived_markdown(r.derived),
            {**r.derived, "flow_scale_px": r.flow_scale_px},
            r.command,
            [str(f) for f in r.files],
        )

    return simulate


def _simulate_controls() -> SimpleNamespace:
    """The Simulate tab's left column: the image, the strength, the optics, the depth and the modulation."""
    with gr.Row():
        source = gr.Radio(list(core.IMAGE_SOURCES), value="sample", label="image")
        sample = gr.Dropdown(list(core.SAMPLES), value="astronaut", label="built-in sample")
    upload = gr.File(
        label="upload an image",
        file_types=sorted(core.IMAGE_SUFFIXES),
        type="filepath",
        height=120,
        visible=False,
    )
    shown = gr.Image(label="input", type="filepath", interactive=False, height=180)
    strength = gr.Radio(list(core.STRENGTHS), value="D/r0", label="strength given as")
    dr0 = gr.Slider(0.1, 10.0, value=DEFAULT_DR0, step=0.05, label=f"D/r0 ({BINS_RULE})")
    cn2 = gr.Number(value=1e-14, label="Cn² (m^-2/3), constant along the path", visible=False)
    with gr.Row():
        aperture = gr.Number(value=SIM_DEFAULTS.aperture_m, label="aperture D (m)")
        wavelength = gr.Textbox(value=SIM_DEFAULTS.wavelength_nm, label="wavelength (nm): one, or three R G B")
    with gr.Row():
        path_length = gr.Number(value=SIM_DEFAULTS.path_length_m, label="path length L (m)")
        ifov = gr.Number(value=0, label="pixel IFOV (µrad), 0 = Nyquist λ/(2D)")
    depth = gr.Radio(list(core.DEPTH_SOURCES), value="prior", label="depth")
    depth_upload = gr.File(
        label="depth map (.png/.tif/.npy; far = large)",
        file_types=[".png", ".tif", ".tiff", ".npy", ".pgm"],
        type="filepath",
        height=120,
        visible=False,
    )
    disparity = gr.Checkbox(value=False, label="the map holds disparity (near = large)", visible=False)
    with gr.Row():
        modulation = gr.Dropdown(list(MODULATIONS), value="power_offset", label="modulation M")
        offset = gr.Slider(0.0, 1.0, value=0.5, step=0.05, label="offset s (Eq. 1)")
    seed = gr.Number(value=0, precision=0, label="seed")
    run = gr.Button("Simulate", variant="primary", elem_id="simulate-button")
    inputs = [source, sample, upload, strength, dr0, cn2, aperture, wavelength, path_length, ifov]
    inputs += [depth, depth_upload, disparity, modulation, offset, seed]
    return SimpleNamespace(
        run=run,
        inputs=inputs,
        source=source,
        sample=sample,
        upload=upload,
        shown=shown,
        strength=strength,
        dr0=dr0,
        cn2=cn2,
        depth=depth,
        depth_upload=depth_upload,
        disparity=disparity,
    )


def _simulate_results() -> list:
    """The Simulate tab's right column: the images, the derived quantities, the command and the downloads (the
    simulate callback's outputs, in its order)."""
    with gr.Row():
        turb = gr.Image(label="I_turb (blur + tilt)", type="filepath", elem_id="sim-turb", height=300)
        tilt = gr.Image(label="I_tilt (tilt only)", type="filepath", height=300)
    with gr.Row():
        flow = gr.Image(label="flow Δ (colour wheel)", type="filepath", height=240)
        depth_view = gr.Image(label="depth (far = white)", type="filepath", height=240)
        modulation_view = gr.Image(label="modulation M (white = 1)", type="filepath", height=240)
    with gr.Row():
        with gr.Column(scale=1, min_width=260):
            derived = gr.Markdown()
        with gr.Column(scale=1, min_width=260):
            command = gr.Code(label="command line (run it in the unpacked zip)", language="shell", **_code_kwargs())
            files = gr.File(label="downloads", file_count="multiple")
    with gr.Accordion("derived quantities (JSON)", open=False):
        derived_json = gr.JSON()
    return [turb, tilt, flow, depth_view, modulation_view, derived, derived_json, command, files]


def _simulate_tab(demo: gr.Blocks, workspace: core.Workspace, limits: core.Limits, guard, show_input) -> None:
    """The Simulate tab (API name ``/simulate``) and its events."""
    simulate = _simulate_callback(workspace, limits, guard)

    @guard
    def show_sample(name):
        path = workspace.new_run("preview") / f"{name}.png"
        write_image(path, core.sample_image(name))
        return path

    with gr.Row():
        with gr.Column(scale=1, min_width=300):
            c = _simulate_controls()
        with gr.Column(scale=2):
            outputs = _simulate_results()
    c.run.click(simulate, c.inputs, outputs, api_name="simulate", concurrency_limit=1)
    c.upload.upload(show_input, c.upload, c.shown, api_name=False)
    c.sample.change(show_sample, c.sample, c.shown, api_name=False)
    c.source.change(lambda v: gr.update(visible=v == "upload"), c.source, c.upload, api_name=False)
    c.strength.change(
        lambda v: (gr.update(visible=v == "D/r0"), gr.update(visible=v != "D/r0")),
        c.strength,
        [c.dr0, c.cn2],
        api_name=False,
    )
    c.depth.change(
        lambda v: (gr.update(visible=v == "upload"),) * 2, c.depth, [c.depth_upload, c.disparity], api_name=False
    )
    demo.load(show_sample, c.sample, c.shown, api_name=False)


def _restore_tab(workspace: core.Workspace, limits: core.Limits, guard, show_input) -> None:
    """The Restore tab (API name ``/restore``): an image or a short video through a model, and its events."""

    @guard
    def show_restore_input(path):
        if path and Path(path).suffix.lower() in _video_suffixes():
            return None  # the first frame is shown with the result
        return show_input(path)

    @guard
    def restore(upload, weights, weights_path, tile, overlap, device, progress=gr.Progress()):  # noqa: B008
        chosen = (weights_path or "").strip() or weights
        progress(0, desc="restoring")
        r = core.run_restore(upload, chosen, workspace, tile, overlap, device, limits, _bars(progress))
        notes = "\n".join(f"* {n}" for n in r.notes)
        pair = (str(r.before), str(r.after))
        niqe_md = core.niqe_markdown(r.niqe) + f"\n\nflow picture: full colour = {r.flow_scale_px:.3g} px"
        niqe_md += "\n\n" + notes if notes else ""
        return (
            pair,
            str(r.flow),
            niqe_md,
            {"niqe": r.niqe, "frames": r.frames, "flow_scale_px": r.flow_scale_px},
            r.command,
            [str(f) for f in r.files],
        )

    def refresh_weights(current):
        found = core.weights_choices()
        value = current if current in {name for name, _ in found} else core.default_weights(found)
        return gr.update(choices=[(_weights_label(n, p), n) for n, p in found], value=value)

    with gr.Row():
        with gr.Column(scale=1, min_width=300):
            r_upload = _image_or_video_upload("image or short video", "restore-upload")
            r_shown = gr.Image(label="input", type="filepath", interactive=False, height=180)
            found = core.weights_choices()
            weights = gr.Dropdown(
                [(_weights_label(n, p), n) for n, p in found],
                value=core.default_weights(found),
                label="weights (found locally)",
            )
            weights_path = gr.Textbox(value="", label="or a local .safetensors path")
            refresh = gr.Button("rescan weights", size="sm")
            with gr.Row():
                tile = gr.Number(value=DEFAULT_TILE_PX, precision=0, label="tile (px)")
                overlap = gr.Number(value=DEFAULT_OVERLAP_PX, precision=0, label="overlap (px)")
            devices = ["cpu"] + (["cuda"] if _cuda() else [])
            device = gr.Dropdown(devices, value=devices[-1], label="device")
            run_restore = gr.Button("Restore", variant="primary", elem_id="restore-button")
        with gr.Column(scale=2):
            compare = gr.ImageSlider(label="input | restored (drag the handle)", type="filepath")
            r_flow = gr.Image(label="predicted flow V̂ (colour wheel)", type="filepath")
            niqe = gr.Markdown()
            r_command = gr.Code(label="command line", language="shell", **_code_kwargs())
            r_files = gr.File(label="downloads", file_count="multiple")
            with gr.Accordion("details (JSON)", open=False):
                r_json = gr.JSON()
    run_restore.click(
        restore,
        [r_upload, weights, weights_path, tile, overlap, device],
        [compare, r_flow, niqe, r_json, r_command, r_files],
        api_name="restore",
        concurrency_limit=1,
    )
    refresh.click(refresh_weights, weights, weights, api_name=False)
    r_upload.upload(show_restore_input, r_upload, r_shown, api_name=False)


def _clip_tab(workspace: core.Workspace, limits: core.Limits, guard) -> None:
    """The Clip tab (API name ``/clip``): a short video, or an image to simulate a clip from, restored as a clip."""

    @guard
    def clip(upload, temporal, dr0, progress=gr.Progress()):  # noqa: B008
        progress(0, desc="restoring the clip")
        r = core.run_clip(upload, workspace, temporal, dr0, limits, _bars(progress))
        notes = "\n".join(f"* {n}" for n in r.notes)
        return (str(r.before), str(r.after)), notes, r.command, [str(f) for f in r.files]

    with gr.Row():
        with gr.Column(scale=1, min_width=300):
            c_upload = _image_or_video_upload(
                "short video (a static scene), or an image to simulate a clip from", "clip-upload"
            )
            c_temporal = gr.Slider(2, 64, value=MEASURED_TEMPORAL, step=1, label="window (frames)")
            c_dr0 = gr.Number(
                value=0,
                label=f"D/r0 for the physics deblur (0 = none; an image is simulated at it, default {DEFAULT_DR0:g})",
            )
            run_clip = gr.Button("Restore clip", variant="primary", elem_id="clip-button")
        with gr.Column(scale=2):
            c_compare = gr.ImageSlider(label="input | restored, middle frame", type="filepath")
            c_notes = gr.Markdown()
            c_command = gr.Code(label="command line", language="shell", **_code_kwargs())
            c_files = gr.File(label="downloads", file_count="multiple")
    run_clip.click(
        clip,
        [c_upload, c_temporal, c_dr0],
        [c_compare, c_notes, c_command, c_files],
        api_name="clip",
        concurrency_limit=1,
    )


def _image_or_video_upload(label: str, elem_id: str) -> gr.File:
    """The upload field of the Restore and Clip tabs: one image or video file."""
    file_types = sorted(core.IMAGE_SUFFIXES | _video_suffixes())
    return gr.File(label=label, file_types=file_types, type="filepath", height=120, elem_id=elem_id)


def _bars(progress: gr.Progress):
    """The command's tqdm bars (read from its stderr by :func:`d2turb.app.jobs.run_command`) → the page's bar."""
    return lambda fraction, desc: progress(fraction, desc=desc)


def _code_kwargs() -> dict:
    return {"wrap_lines": True} if "wrap_lines" in inspect.signature(gr.Code.__init__).parameters else {}


def _video_suffixes() -> set[str]:
    return set(VIDEO_SUFFIXES)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def _theme():
    font = ["ui-sans-serif", "system-ui", "sans-serif"]  # local fonts: the page fetches nothing from the internet
    mono = ["ui-monospace", "monospace"]
    return gr.themes.Default(font=font, font_mono=mono)


def _blocks_kwargs() -> dict:
    """gradio < 6 takes theme (and analytics) in Blocks(), gradio 6 in launch()."""
    params = inspect.signature(gr.Blocks.__init__).parameters
    kwargs = {"analytics_enabled": False}
    if "theme" in params:
        kwargs["theme"] = _theme()
    return kwargs


def _launch_kwargs(host: str, port: int | None, workspace: core.Workspace) -> dict:
    params = inspect.signature(gr.Blocks.launch).parameters
    wanted = {
        "server_name": host,
        "server_port": port,
        "show_error": False,
        "allowed_paths": [str(workspace.root)],
        "max_file_size": MAX_UPLOAD,
        "share": False,
        "ssr_mode": False,
        "theme": _theme(),
        "prevent_thread_lock": True,
        "quiet": False,
    }
    return {k: v for k, v in wanted.items() if k in params}


def serve(host: str = "127.0.0.1", port: int | None = None, workspace: core.Workspace | None = None, limits=None):
    """Start the page and return ``(blocks, url)``; the server runs in a background thread until
    ``blocks.close()``. Binds to ``host`` (localhost by default)."""
    workspace = workspace or core.Workspace()
    demo = build_app(workspace, limits)
    demo.queue(default_concurrency_limit=1)
    _, url, _ = demo.launch(**_launch_kwargs(host, port, workspace))
    return demo, url
