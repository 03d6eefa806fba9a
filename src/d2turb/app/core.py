"""The app's work, in plain Python (no gradio): each run calls the library job that ``d2turb simulate`` /
``simulate-video`` / ``restore`` run (:mod:`d2turb.data.simulate`, :mod:`d2turb.restore.files`) inside the app's temp
folder, with the values of the command line it shows, plus the pictures and numbers the page shows.

The command line and the call are built from the same checked values, so the command pasted into a shell next to
the downloaded input writes the same files (tests/test_app.py runs it). Every problem a user can cause raises
:class:`d2turb.errors.D2TurbError` with a one-line message; the UI layer turns it into a message in the page.
"""

from __future__ import annotations

import json
import math
import re
import shlex
import shutil
import tempfile
import threading
import uuid
import zipfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from d2turb import __version__
from d2turb.data.samples import SAMPLES, sample_images
from d2turb.data.simulate import simulate_files, simulate_video
from d2turb.defaults import DEFAULT_APERTURE_M, DEFAULT_DEVICE, DEFAULT_PATH_LENGTH_M, DEFAULT_WAVELENGTH_M
from d2turb.depth import depth_for_image
from d2turb.depth.io import DEPTH_SUFFIXES
from d2turb.errors import D2TurbError
from d2turb.eval.niqe import niqe
from d2turb.eval.report import fit_cell, flow_to_rgb
from d2turb.io import IMAGE_SUFFIXES, image_size, read_image, write_image, write_json, write_text
from d2turb.models.hub import (
    IDENTITY_NAME,
    RECOMMENDED_WEIGHTS,
    resolve_weights,
    shipped_weights_dir,
    weights_search_path,
)
from d2turb.models.weights import WEIGHTS_SUFFIX
from d2turb.restore.files import restore_clip_files, restore_files
from d2turb.sim import MODULATIONS, depth_modulation, derived_quantities, make_params
from d2turb.video import VIDEO_SUFFIXES, iter_video, video_size

STRENGTHS = ("D/r0", "Cn²")
DEPTH_SOURCES = ("none", "prior", "upload")
IMAGE_SOURCES = ("sample", "upload")
PREVIEW_SIDE = 2048  # pictures shown in the page are downscaled to this longer side (downloads keep full size)


@dataclass(frozen=True)
class Limits:
    """What the app accepts (a local app on a laptop: the simulator's memory grows with the image area)."""

    sim_pixels: int = 1 << 21  # 2.1 MP: 1920x1080 fits
    restore_pixels: int = 25_000_000  # 6000x4000 fits; restore is tiled, ~14 float32 per pixel besides the model
    video_frames: int = 150


class Workspace:
    """The app's one temp folder: uploads (gradio's cache), every run's inputs and outputs. Removed by
    :meth:`cleanup` (the ``d2turb app`` command does that on exit)."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(tempfile.mkdtemp(prefix="d2turb-app-", dir=root)).resolve()
        self._lock = threading.Lock()
        self._count = 0

    def new_run(self, kind: str) -> Path:
        with self._lock:
            self._count += 1
            n = self._count
        run = self.root / "runs" / f"{kind}-{n:04d}-{uuid.uuid4().hex[:6]}"
        run.mkdir(parents=True)
        return run

    def cleanup(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)


def prepare_environment(workspace: Workspace) -> None:
    """Point gradio's upload cache (and matplotlib's config) into the workspace and switch gradio's analytics off
    (nothing leaves the machine). Call before ``import gradio``: gradio reads ``GRADIO_TEMP_DIR`` on import."""
    import os

    os.environ["GRADIO_TEMP_DIR"] = str(workspace.root / "gradio")
    os.environ["GRADIO_ANALYTICS_ENABLED"] = "False"
    os.environ.setdefault("MPLCONFIGDIR", str(workspace.root / "matplotlib"))


# ---- small helpers ---------------------------------------------------------------------------------------------
def safe_stem(name: str, default: str = "image") -> str:
    """A file stem that is safe on a command line and cannot be read as an option (no leading '-')."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(str(name)).stem).strip("._")[:64]
    if not stem:
        return default
    return stem if stem[0].isalnum() else f"{default}_{stem}"


def fmt_float(x: float) -> str:
    """Shortest text that parses back to the same float (``repr``), so a command line is exact."""
    return repr(float(x))


def _number(name: str, value, positive: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise D2TurbError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(v) or (positive and v <= 0):
        raise D2TurbError(f"{name} must be {'positive and ' if positive else ''}finite, got {value!r}")
    return float(f"{v:.12g}")  # drops the browser's float noise (a slider's 3.0500000000000003 → 3.05)


def _scaled(name: str, text, exponent: int) -> float:
    """A number typed in a unit (nm: exponent -9, µrad: -6) → SI through its decimal text, so that "525" nm is
    exactly the float of ``525e-9`` (the CLI's default and what a typed ``--wavelength 525e-9`` gives)."""
    m = re.fullmatch(r"([0-9.]+)(?:e([-+]?[0-9]+))?", repr(_number(name, text)))  # a positive finite float's repr
    return float(f"{m[1]}e{int(m[2] or 0) + exponent}")


def parse_wavelengths_nm(text) -> list[float]:
    """'525' or '620 530 460' (nm; commas allowed) → wavelengths in metres."""
    tokens = [t for t in re.split(r"[\s,;]+", str(text or "").strip()) if t]
    if len(tokens) not in (1, 3):
        raise D2TurbError(f"wavelength: give one value or three (R G B) in nm, got {text!r}")
    return [_scaled("wavelength (nm)", t, -9) for t in tokens]


def _known(suffixes) -> str:
    return " ".join(sorted(suffixes))


def check_pixels(name: str, width: int, height: int, limit: int) -> None:
    if width * height > limit:
        raise D2TurbError(
            f"{name}: {width}x{height} is too large for the app ({width * height / 1e6:.1f} MP > "
            f"{limit / 1e6:.1f} MP); use the command line, which has no limit"
        )


def _check_status(status: int, argv: list[str]) -> None:
    """A job's exit status as the command line would end: nonzero (some inputs failed) is an error in the page."""
    if status:
        raise D2TurbError(f"d2turb {argv[0]} failed (exit status {status})")


def write_command(path: Path, *argvs: list[str]) -> str:
    """The command lines as text (``d2turb ...``, one per argv, run in order) and as an executable script ``path``."""
    cmd = "\n".join(shlex.join(["d2turb", *argv]) for argv in argvs)
    write_text(path, f"#!/bin/sh\n# written by d2turb {__version__} app; run it in this folder\n{cmd}\n")
    path.chmod(0o755)
    return cmd


def bundle(run: Path, name: str) -> Path:
    """Zip everything of a run (inputs, out/, views/, command.sh) into run/name.zip."""
    target = run / f"{name}.zip"
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_STORED) as zf:
        for p in sorted(run.rglob("*")):
            if p.is_file() and p != target:
                zf.write(p, Path(name) / p.relative_to(run))
    return target


def preview(image: torch.Tensor, path: Path, source: Path | None = None) -> Path:
    """(C,H,W) in [0,1] as an 8-bit PNG for the page, downscaled to PREVIEW_SIDE if larger; ``source``: a PNG
    that already holds this image, returned as is when no downscaling is needed."""
    if max(image.shape[-2:]) <= PREVIEW_SIDE:
        if source is not None:
            return source
        write_image(path, image)
    else:
        write_image(path, fit_cell(image.float(), PREVIEW_SIDE))
    return path


def flow_view(flow: torch.Tensor, path: Path) -> tuple[Path, float]:
    """Colour-wheel picture of a (2,H,W) flow with the wheel as a legend in the bottom-right corner; returns the
    path and the magnitude (px) that maps to full saturation."""
    scale = float(flow.norm(dim=0).max())
    rgb = flow_to_rgb(flow, max_px=scale if scale > 0 else 1.0)
    h, w = rgb.shape[-2:]
    r = max(8, min(h, w) // 8)
    if min(h, w) >= 4 * r:
        ys, xs = torch.meshgrid(torch.arange(2 * r + 1) - r, torch.arange(2 * r + 1) - r, indexing="ij")
        wheel = flow_to_rgb(torch.stack([xs, ys]).float(), max_px=float(r))
        inside = (xs**2 + ys**2) <= r * r
        patch = rgb[:, h - 2 * r - 3 : h - 2, w - 2 * r - 3 : w - 2]  # bottom right
        patch.copy_(torch.where(inside, wheel, patch))
    return preview(rgb, path), scale


# ---- derived quantities (d2turb.sim.derived_quantities) ------------------------------------------------------
_DERIVED_ROWS = (
    ("dr0", "D/r0", "{:.3g}", ""),
    ("bin", "strength bin", "{}", ""),
    ("r0_m", "Fried parameter r0", "{:.3g}", "m"),
    ("cn2", "Cn² (constant along the path)", "{:.3g}", "m^-2/3"),
    ("theta0_urad", "isoplanatic angle θ0", "{:.3g}", "µrad"),
    ("theta0_px", "θ0 in pixels", "{:.3g}", "px"),
    ("tilt_sigma_px", "tilt σ per axis (M = 1)", "{:.3g}", "px"),
    ("tilt_sigma_px_mean_m", "tilt σ at the mean M", "{:.3g}", "px"),
    ("mean_modulation", "mean modulation M", "{:.3g}", ""),
    ("footprint_px", "aperture footprint D/(ifov·L)", "{:.3g}", "px"),
    ("samples_per_lambda_d", "pixels per λ/D (2 = Nyquist)", "{:.3g}", ""),
    ("ifov_urad", "pixel IFOV", "{:.4g}", "µrad"),
)


def derived_markdown(d: dict) -> str:
    lines = ["| quantity | value |", "|---|---|"]
    for key, label, form, unit in _DERIVED_ROWS:
        if key in d:
            lines.append(f"| {label} | {form.format(d[key])} {unit} |")
    return "\n".join(lines)


# ---- simulate --------------------------------------------------------------------------------------------------
@dataclass
class SimSettings:
    """The Simulate tab's controls. Units as shown in the page: wavelength nm, IFOV µrad (0 or None = Nyquist)."""

    source: str = "sample"
    sample: str = "astronaut"
    upload: str | None = None
    strength: str = "D/r0"
    dr0: float = 3.0
    cn2: float = 1e-14
    aperture_m: float = DEFAULT_APERTURE_M
    wavelength_nm: str = f"{DEFAULT_WAVELENGTH_M * 1e9:g}"  # "525": parsed back to exactly DEFAULT_WAVELENGTH_M
    path_length_m: float = DEFAULT_PATH_LENGTH_M
    ifov_urad: float | None = None
    depth: str = "none"
    depth_upload: str | None = None
    disparity: bool = False
    modulation: str = "power_offset"
    offset_s: float = 0.5
    seed: int = 0


@dataclass
class SimOutput:
    turb: Path
    tilt: Path
    flow: Path  # colour-wheel picture
    depth: Path | None
    modulation: Path
    derived: dict
    command: str
    files: list[Path]
    run_dir: Path
    flow_scale_px: float = 0.0
    warnings: list[str] = field(default_factory=list)


@lru_cache(maxsize=1)
def _samples() -> dict:
    return sample_images()


def sample_image(name: str) -> torch.Tensor:
    """A built-in sample (3, 192, 256) in [0, 1]: the demo's images (``SAMPLES``)."""
    if name not in SAMPLES:
        raise D2TurbError(f"unknown sample {name!r}; choose one of {', '.join(SAMPLES)}")
    return _samples()[name]


@dataclass(frozen=True)
class SimValues:
    """The checked values of one Simulate run, in SI units: both its ``d2turb simulate`` command line
    (:func:`simulate_argv`) and its library call are made from these. ``depth``: none, prior or the depth file's
    name in the run folder."""

    seed: int
    dr0: float | None
    cn2: float | None
    depth: str
    disparity: bool
    aperture_m: float
    wavelength_m: list[float]
    path_length_m: float
    ifov_rad: float | None
    modulation: str
    offset_s: float

    def params(self):
        """The simulator's :class:`~d2turb.sim.TurbulenceParams` (one-line D2TurbError for impossible values)."""
        return make_params(
            self.aperture_m,
            self.wavelength_m,
            self.path_length_m,
            dr0=self.dr0,
            cn2=self.cn2,
            ifov_rad=self.ifov_rad,
            offset_s=self.offset_s,
            modulation=self.modulation,
        )


def sim_values(s: SimSettings, depth_name: str | None) -> SimValues:
    """The page's settings checked and converted (nm, µrad → m, rad), each problem a one-line D2TurbError."""
    seed = _number("seed", s.seed, positive=False)
    if not (seed.is_integer() and 0 <= seed < 2**63):
        raise D2TurbError(f"seed must be a whole number in [0, 2^63), got {s.seed!r}")
    if s.strength == "D/r0":
        dr0, cn2 = _number("D/r0", s.dr0), None
    elif s.strength == "Cn²":
        dr0, cn2 = None, _number("Cn²", s.cn2)
    else:
        raise D2TurbError(f"strength must be one of {', '.join(STRENGTHS)}, got {s.strength!r}")
    if s.depth == "upload":
        if not depth_name:
            raise D2TurbError("depth source 'upload': upload a depth map first")
        depth, disparity = depth_name, bool(s.disparity)
    elif s.depth in ("none", "prior"):
        depth, disparity = s.depth, False
    else:
        raise D2TurbError(f"depth source must be one of {', '.join(DEPTH_SOURCES)}, got {s.depth!r}")
    aperture = _number("aperture", s.aperture_m)
    wavelengths = parse_wavelengths_nm(s.wavelength_nm)
    path_length = _number("path length", s.path_length_m)
    ifov = None if s.ifov_urad in (None, "", 0, 0.0) else _scaled("pixel IFOV (µrad)", s.ifov_urad, -6)
    if s.modulation not in MODULATIONS:
        raise D2TurbError(f"modulation must be one of {', '.join(MODULATIONS)}, got {s.modulation!r}")
    offset = _number("offset s", s.offset_s, positive=False)
    return SimValues(
        int(seed), dr0, cn2, depth, disparity, aperture, wavelengths, path_length, ifov, s.modulation, offset
    )


def simulate_argv(s: SimSettings | SimValues, input_name: str, depth_name: str | None = None, out: str = "out"):
    """The ``d2turb simulate`` arguments (without ``d2turb``) for these settings (or their checked values)."""
    v = s if isinstance(s, SimValues) else sim_values(s, depth_name)
    argv = ["simulate", input_name, "--out", out, "--seed", str(v.seed)]
    argv += ["--dr0", fmt_float(v.dr0)] if v.dr0 is not None else ["--cn2", fmt_float(v.cn2)]
    argv += ["--depth", v.depth] + (["--disparity"] if v.disparity else [])
    argv += ["--aperture", fmt_float(v.aperture_m)]
    argv += ["--wavelength", *[fmt_float(w) for w in v.wavelength_m]]
    argv += ["--path-length", fmt_float(v.path_length_m)]
    if v.ifov_rad is not None:
        argv += ["--ifov", fmt_float(v.ifov_rad)]
    argv += ["--modulation", v.modulation, "--offset", fmt_float(v.offset_s), "--save-flow"]
    return argv


def _prepare_sim_input(s: SimSettings, run: Path, limits: Limits) -> tuple[str, torch.Tensor]:
    if s.source == "sample":
        image = sample_image(s.sample)
        name = f"{s.sample}.png"
        write_image(run / name, image)  # 8-bit, as the command line will read it
    elif s.source == "upload":
        if not s.upload:
            raise D2TurbError("image source 'upload': upload an image first (or choose a sample)")
        src = Path(s.upload)
        if src.suffix.lower() not in IMAGE_SUFFIXES:
            raise D2TurbError(f"{src.name}: not an image file type ({_known(IMAGE_SUFFIXES)})")
        w, h = image_size(src)
        check_pixels(src.name, w, h, limits.sim_pixels)
        name = safe_stem(src.name) + src.suffix.lower()
        shutil.copyfile(src, run / name)  # the original bytes: the command line reads exactly what the app read
    else:
        raise D2TurbError(f"image source must be one of {', '.join(IMAGE_SOURCES)}, got {s.source!r}")
    return name, read_image(run / name)


def run_simulation(s: SimSettings, workspace: Workspace, limits: Limits | None = None) -> SimOutput:
    """Simulate turbulence as the page asks: runs ``d2turb simulate`` (in-process) in a fresh run folder and
    prepares the pictures (I_turb, I_tilt, flow, depth, M), the derived quantities and the downloads."""
    limits = limits or Limits()
    run = workspace.new_run("simulate")
    name, image = _prepare_sim_input(s, run, limits)
    stem = Path(name).stem
    warnings: list[str] = []
    depth_name = None
    if s.depth == "upload" and s.depth_upload:
        src = Path(s.depth_upload)
        if src.suffix.lower() not in DEPTH_SUFFIXES:
            raise D2TurbError(f"{src.name}: not a depth map file type ({_known(DEPTH_SUFFIXES)})")
        depth_name = f"{stem}_depthmap{src.suffix.lower()}"
        shutil.copyfile(src, run / depth_name)
    values = sim_values(s, depth_name)
    argv = simulate_argv(values, name)
    # check what the job will meet before running it, with the user's file names in messages
    params = values.params()
    depth_spec = str(run / depth_name) if values.depth == depth_name else values.depth
    depth = depth_for_image(depth_spec, run / name, image, is_disparity=values.disparity)  # refuses another aspect
    status = simulate_files(
        [run / name],
        run / "out",
        params,
        depth=depth_spec,
        disparity=values.disparity,
        seed=values.seed,
        save_flow=True,
    )
    _check_status(status, argv)
    command = write_command(run / "command.sh", argv)

    out = run / "out"
    meta_path = out / f"{stem}_meta.json"
    meta = json.loads(meta_path.read_text())
    meta.update(input=name, depth=argv[argv.index("--depth") + 1])  # as the command line, run in the bundle, writes
    write_json(meta_path, meta)
    flow = torch.from_numpy(np.load(out / f"{stem}_flow.npy"))
    views = run / "views"
    modulation = depth_modulation(depth[None], params.modulation, params.offset_s)[0] if depth is not None else None
    if modulation is None:
        modulation = torch.ones(1, *image.shape[-2:])
    flow_png, scale = flow_view(flow, views / "flow.png")
    result = SimOutput(
        turb=preview(read_image(out / f"{stem}_turb.png"), views / "turb.png", out / f"{stem}_turb.png"),
        tilt=preview(read_image(out / f"{stem}_tilt.png"), views / "tilt.png", out / f"{stem}_tilt.png"),
        flow=flow_png,
        depth=preview(depth, views / "depth.png") if depth is not None else None,
        modulation=preview(modulation, views / "modulation.png"),
        derived=derived_quantities(params, meta["mean_modulation"]),
        command=command,
        files=[],
        run_dir=run,
        flow_scale_px=scale,
        warnings=warnings,
    )
    zipped = bundle(run, f"d2turb_simulate_{stem}")
    result.files = [zipped, *(out / f"{stem}_{k}" for k in ("turb.png", "tilt.png", "flow.npy", "meta.json"))]
    result.files.append(run / "command.sh")
    return result


# ---- restore ---------------------------------------------------------------------------------------------------
def weights_choices() -> list[tuple[str, Path | None]]:
    """(name, file) of every weights name ``resolve_weights`` finds in its folders (in its order: the first folder
    holding a name wins), after the identity baseline ``("input", None)``."""
    found: dict[str, Path] = {}
    for folder in dict.fromkeys(p.parent for p in weights_search_path("x")):
        for f in sorted(folder.glob(f"*{WEIGHTS_SUFFIX}")) if folder.is_dir() else []:
            if f.stem in found or f.stem == IDENTITY_NAME:
                continue
            try:
                if resolve_weights(f.stem) == f:
                    found[f.stem] = f
            except D2TurbError:  # not a valid name (e.g. a space in it): only usable as a path
                continue
    return [(IDENTITY_NAME, None), *found.items()]


def default_weights(choices: list[tuple[str, Path | None]]) -> str:
    """The weights preselected in the page: the recommended shipped one (``RECOMMENDED_WEIGHTS``), else the first
    shipped one, else the first found, else "input"."""
    found = [(name, path) for name, path in choices if path is not None]
    shipped = [name for name, path in found if path.parent == shipped_weights_dir()]
    shipped.sort(key=lambda name: name != RECOMMENDED_WEIGHTS)
    return (shipped or [name for name, _ in found] or [choices[0][0]])[0]


@dataclass
class RestoreOutput:
    before: Path
    after: Path
    flow: Path
    niqe: dict
    command: str
    files: list[Path]
    run_dir: Path
    frames: int = 1
    flow_scale_px: float = 0.0
    notes: list[str] = field(default_factory=list)


def _niqe(image: torch.Tensor) -> float | str:
    try:
        return float(niqe(image))
    except D2TurbError as exc:
        return f"n/a ({exc})"


def restore_argv(input_name: str, weights: str, tile: int, overlap: int, device: str, out: str = "out") -> list[str]:
    """The ``d2turb restore`` arguments (without ``d2turb``); ``device`` "cpu" is left to the command's default."""
    argv = ["restore", input_name, "--weights", weights, "--out", out, "--tile", str(tile), "--overlap", str(overlap)]
    return argv + (["--device", device] if device != "cpu" else []) + ["--save-flow"]


def run_restore(
    upload: str | None,
    weights: str,
    workspace: Workspace,
    tile: int = 512,
    overlap: int = 64,
    device: str = "cpu",
    limits: Limits | None = None,
) -> RestoreOutput:
    """Restore an uploaded image or short video with ``d2turb restore`` (in-process, same tiling, tqdm progress);
    ``weights``: "input", a name from :func:`weights_choices` or a .safetensors path."""
    limits = limits or Limits()
    if not upload:
        raise D2TurbError("upload an image or a short video first")
    src = Path(upload)
    if not src.is_file():
        raise D2TurbError(f"{src.name}: the uploaded file is gone; upload it again")
    weights = str(weights or "").strip()
    if not weights:
        raise D2TurbError("choose weights (or 'input' for the identity baseline)")
    resolved = resolve_weights(weights)  # one-line error for a missing name or file
    if isinstance(resolved, Path) and weights != resolved.stem:
        weights = str(resolved.resolve())  # a path: absolute, so the command works from any folder
    for name, value in (("tile", tile), ("overlap", overlap)):
        if not float(value).is_integer():
            raise D2TurbError(f"{name} must be a whole number of pixels, got {value}")
    tile, overlap = int(tile), int(overlap)

    is_video = src.suffix.lower() in VIDEO_SUFFIXES
    if is_video:
        frames, w, h = video_size(src)
        if frames > limits.video_frames:
            raise D2TurbError(
                f"{src.name}: {frames} frames is more than the app takes ({limits.video_frames}); "
                "trim the video or use the command line"
            )
    elif src.suffix.lower() in IMAGE_SUFFIXES:
        frames = 1
        w, h = image_size(src)
    else:
        raise D2TurbError(f"{src.name}: not an image or video file type ({_known(IMAGE_SUFFIXES | VIDEO_SUFFIXES)})")
    check_pixels(src.name, w, h, limits.restore_pixels)

    run = workspace.new_run("restore")
    name = safe_stem(src.name) + src.suffix.lower()
    stem = Path(name).stem
    shutil.copyfile(src, run / name)
    if is_video:
        first = next((f for _, f in iter_video(run / name)), None)
        if first is None:
            raise D2TurbError(f"{src.name}: the video has no frames")
    else:
        first = read_image(run / name)
    argv = restore_argv(name, weights, tile, overlap, device)
    job_device = device if "--device" in argv else DEFAULT_DEVICE  # as the command line runs
    status = restore_files(
        [run / name], run / "out", weights, tile=tile, overlap=overlap, device=job_device, save_flow=True
    )
    _check_status(status, argv)
    command = write_command(run / "command.sh", argv)

    out = run / "out"
    key = f"{stem}_000000" if is_video else stem
    restored = read_image(out / f"{key}_restored.png")
    flow = torch.from_numpy(np.load(out / f"{key}_flow.npy"))
    views = run / "views"
    flow_png, scale = flow_view(flow, views / "flow.png")
    notes = []
    if is_video:
        notes.append(f"{frames} frames restored; the page shows the first, the download holds all")
    if max(first.shape[-2:]) > PREVIEW_SIDE:
        notes.append(f"pictures in the page are downscaled to {PREVIEW_SIDE} px; downloads are full size")
    result = RestoreOutput(
        before=preview(first, views / "input.png"),
        after=preview(restored, views / "restored.png", out / f"{key}_restored.png"),
        flow=flow_png,
        niqe={"input": _niqe(first), "restored": _niqe(restored)},
        command=command,
        files=[],
        run_dir=run,
        frames=frames,
        flow_scale_px=scale,
        notes=notes,
    )
    zipped = bundle(run, f"d2turb_restore_{stem}")
    result.files = [zipped, out / f"{key}_restored.png", out / f"{key}_flow.npy", run / "command.sh"]
    return result


def niqe_markdown(values: dict) -> str:
    def cell(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    return (
        "| NIQE (lower is better) | value |\n|---|---|\n"
        f"| input | {cell(values['input'])} |\n| restored | {cell(values['restored'])} |\n\n{NIQE_CAVEAT}"
    )


@dataclass
class ClipOutput:
    before: Path  # the middle input frame
    after: Path  # the middle restored frame
    command: str  # the command lines that reproduce the run (simulate-video first for an image)
    files: list[Path]
    run_dir: Path
    frames: int
    notes: list[str] = field(default_factory=list)


CLIP_SIM_FRAMES = 32  # frames simulated from an uploaded image


def clip_argv(clip: str, temporal: int, dr0: float | None, out: str = "out") -> list[str]:
    """The ``d2turb restore --temporal`` arguments (without ``d2turb``); no ``dr0``: fusion without deblurring."""
    argv = ["restore", clip, "--temporal", str(temporal), "--out", out, "--save-intermediate"]
    return argv + (["--dr0", f"{dr0:g}"] if dr0 else ["--deblur", "none"])


def run_clip(
    upload: str | None,
    workspace: Workspace,
    temporal: int = 32,
    dr0: float | None = None,
    limits: Limits | None = None,
) -> ClipOutput:
    """Clip restoration in the page: an uploaded video is restored across frames (``d2turb restore --temporal``);
    an uploaded image is first made into a turbulent clip of ``CLIP_SIM_FRAMES`` frames at ``dr0``
    (``d2turb simulate-video``, wind 2 m/s, boiling 0.1) and then restored with that known D/r0. ``dr0`` empty or
    0 with a video: fusion without deblurring."""
    limits = limits or Limits()
    if not upload:
        raise D2TurbError("upload a short video (or an image to simulate a clip from) first")
    src = Path(upload)
    if not src.is_file():
        raise D2TurbError(f"{src.name}: the uploaded file is gone; upload it again")
    if not float(temporal).is_integer() or temporal < 2:
        raise D2TurbError(f"the window must be a whole number of frames >= 2, got {temporal}")
    temporal = int(temporal)
    dr0 = float(dr0) if dr0 else None
    run = workspace.new_run("clip")
    name = safe_stem(src.name) + src.suffix.lower()
    shutil.copyfile(src, run / name)
    commands, notes = [], []
    if src.suffix.lower() in VIDEO_SUFFIXES:
        frames, w, h = video_size(run / name)
        if frames == 0:  # containers that do not store it (mkv, webm): count by decoding
            frames = sum(1 for _ in iter_video(run / name))
        if frames > limits.video_frames:
            raise D2TurbError(
                f"{src.name}: {frames} frames is more than the app takes ({limits.video_frames}); "
                "trim the video or use the command line"
            )
        check_pixels(src.name, w, h, limits.restore_pixels)
        clip, mp4 = name, f"{Path(name).stem}_restored.mp4"
    elif src.suffix.lower() in IMAGE_SUFFIXES:
        w, h = image_size(src)
        check_pixels(src.name, w, h, limits.sim_pixels)
        sim_dr0 = float(f"{dr0 or 3.0:g}")  # the value the command line below gives
        sim = ["simulate-video", name, "--out", "clip", "--frames", str(CLIP_SIM_FRAMES), "--dr0", f"{sim_dr0:g}"]
        sim += ["--wind", "2", "--boil", "0.1", "--no-mp4"]
        params = make_params(dr0=sim_dr0)
        status = simulate_video(run / name, run / "clip", params, frames=CLIP_SIM_FRAMES, wind=2.0, boil=0.1, mp4=False)
        _check_status(status, sim)
        commands.append(sim)
        clip, frames, mp4, dr0 = "clip/turb", CLIP_SIM_FRAMES, "turb_restored.mp4", sim_dr0
        notes.append(f"a {frames}-frame clip was simulated from the image at D/r0 = {sim_dr0:g} and restored with it")
    else:
        raise D2TurbError(f"{src.name}: not a video or image file type ({_known(IMAGE_SUFFIXES | VIDEO_SUFFIXES)})")
    argv = clip_argv(clip, temporal, dr0)
    job_dr0 = float(f"{dr0:g}") if dr0 else None  # as the command line gives it
    deblur = "auto" if dr0 else "none"
    status = restore_clip_files(run / clip, run / "out", temporal, deblur=deblur, dr0=job_dr0, save_intermediate=True)
    _check_status(status, argv)
    commands.append(argv)
    text = write_command(run / "command.sh", *commands)
    out, views = run / "out", run / "views"
    restored_all = sorted(out.glob("*_restored.png"))  # frame names are zero-padded: sorted = in order
    if not restored_all:
        raise D2TurbError(f"{src.name}: the clip gave no restored frame")
    middle = len(restored_all) // 2
    restored_png = restored_all[middle]
    if src.suffix.lower() in VIDEO_SUFFIXES:
        before_img = next(f for i, f in iter_video(run / name) if i == middle)
    else:
        before_img = read_image(run / clip / restored_png.name.replace("_restored.png", ".png"))
    if not dr0:
        notes.append("no D/r0 given: the frames are registered and fused, not deblurred")
    result = ClipOutput(
        before=preview(before_img, views / "input.png"),
        after=preview(read_image(restored_png), views / "restored.png", restored_png),
        command=text,
        files=[],
        run_dir=run,
        frames=frames,
        notes=notes,
    )
    zipped = bundle(run, f"d2turb_clip_{Path(name).stem}")
    result.files = [zipped, restored_png, run / "command.sh"] + ([out / mp4] if (out / mp4).is_file() else [])
    return result


# what a no-reference score is worth (docs/metrics.md, "What NIQE and PIQE show, and what they do not")
NIQE_CAVEAT = (
    "NIQE compares image statistics with clean photos, not with the scene: a hint, not proof of restoration "
    "(a broken model's output can score better than its input; judge by the pictures, see docs/metrics.md)."
)
