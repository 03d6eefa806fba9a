"""The app's work, in plain Python (no gradio): each run is the real ``d2turb simulate`` / ``d2turb restore`` command
line, executed in-process inside the app's temp folder, plus the pictures and numbers the page shows.

Running the CLI itself (parsed by ``d2turb.cli.build_parser``) makes the command line shown in the page the one
definition of what the app did: pasted into a shell next to the downloaded input it writes the same files. Every
problem a user can cause raises :class:`d2turb.errors.D2TurbError` with a one-line message; the UI layer turns it
into a message in the page.
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
from d2turb.cli import build_parser
from d2turb.commands.demo import sample_images
from d2turb.commands.simulate import make_params
from d2turb.depth import depth_for_image
from d2turb.depth.io import DEPTH_SUFFIXES
from d2turb.errors import D2TurbError
from d2turb.eval.niqe import niqe
from d2turb.eval.report import fit_cell, flow_to_rgb
from d2turb.io import IMAGE_SUFFIXES, read_image, write_image, write_json, write_text
from d2turb.models.hub import (
    IDENTITY_NAME,
    RECOMMENDED_WEIGHTS,
    WEIGHTS_SUFFIX,
    resolve_weights,
    shipped_weights_dir,
    weights_search_path,
)
from d2turb.sim import MODULATIONS, Simulator, depth_modulation, dr0_bin, fried_r0_spherical
from d2turb.sim.geometry import footprint_px
from d2turb.video import VIDEO_HINT, VIDEO_SUFFIXES, iter_video

SAMPLES = ("astronaut", "coffee", "chelsea", "chart")  # d2turb.commands.demo.sample_images
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


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels (refuses decompression bombs)."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            return img.size
    except Image.DecompressionBombError as exc:
        raise D2TurbError(f"{path.name}: image is far too large ({exc})") from exc
    except Exception as exc:  # noqa: BLE001 - any decoder failure is "not an image" to the user
        raise D2TurbError(f"{path.name}: cannot read image ({exc.__class__.__name__}: {exc})") from exc


def check_pixels(name: str, width: int, height: int, limit: int) -> None:
    if width * height > limit:
        raise D2TurbError(
            f"{name}: {width}x{height} is too large for the app ({width * height / 1e6:.1f} MP > "
            f"{limit / 1e6:.1f} MP); use the command line, which has no limit"
        )


def parse_cli(argv: list[str]):
    """The real ``d2turb`` parser on ``argv``; argparse's exit becomes a D2TurbError."""
    try:
        return build_parser().parse_args(argv)
    except SystemExit as exc:
        raise D2TurbError(f"invalid parameters for d2turb {argv[0]}") from exc


def run_cli(argv: list[str]) -> None:
    """Run one d2turb command in-process, as ``d2turb.cli.main`` would (errors stay D2TurbError)."""
    args = parse_cli(argv)
    rc = args.func(args)
    if rc:
        raise D2TurbError(f"d2turb {argv[0]} failed (exit status {rc})")


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


# ---- derived quantities ----------------------------------------------------------------------------------------
def isoplanatic_angle(cn2: float, path_length_m: float, wavelength_m: float) -> float:
    """θ0 = [2.914 k² ∫ Cn²(z) z^(5/3) dz]^(−3/5) for constant Cn² over a path of length L:
    [2.914·(3/8)·k² Cn² L^(8/3)]^(−3/5) rad (= 0.314 r0_spherical / L; Fried, JOSA 72, 1982)."""
    k = 2 * math.pi / wavelength_m
    return (2.914 * 3 / 8 * k * k * cn2 * path_length_m ** (8 / 3)) ** (-3 / 5)


def derived_quantities(params, mean_modulation: float | None = None) -> dict:
    """What a parameter set means physically. ``params``: :class:`d2turb.sim.TurbulenceParams` (D/r0 resolved).

    Keys: dr0, r0_m, cn2 (spherical-wave value that gives this r0), theta0_urad / theta0_px (isoplanatic angle),
    tilt_sigma_px (per axis, where M = 1; the simulator's own scale), footprint_px (tilt correlation scale),
    samples_per_lambda_d (q = λ/(D·ifov), 2 = Nyquist), ifov_urad, bin; with ``mean_modulation`` also
    tilt_sigma_px_mean_m (σ at the mean M: Δ = M·Δ0, Eq. 5)."""
    lam, length = params.reference_wavelength, params.path_length_m
    r0 = params.r0_m
    cn2 = (fried_r0_spherical(1.0, length, lam) / r0) ** (5 / 3)  # r0 ∝ Cn²^(−3/5)
    theta0 = isoplanatic_angle(cn2, length, lam)
    sim = Simulator(params)
    sigma = sim.tilt_std * sim.px_per_a2 * params.dr0 ** (5 / 6)
    out = {
        "dr0": params.dr0,
        "bin": dr0_bin(params.dr0),
        "r0_m": r0,
        "cn2": cn2,
        "theta0_urad": theta0 * 1e6,
        "theta0_px": theta0 / params.ifov_rad,
        "tilt_sigma_px": sigma,
        "footprint_px": footprint_px(params),
        "samples_per_lambda_d": lam / (params.aperture_m * params.ifov_rad),
        "ifov_urad": params.ifov_rad * 1e6,
    }
    if mean_modulation is not None:
        out["mean_modulation"] = float(mean_modulation)
        out["tilt_sigma_px_mean_m"] = sigma * float(mean_modulation)
    return out


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
    aperture_m: float = 0.1
    wavelength_nm: str = "525"
    path_length_m: float = 1000.0
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


def simulate_argv(s: SimSettings, input_name: str, depth_name: str | None, out: str = "out") -> list[str]:
    """The ``d2turb simulate`` arguments (without ``d2turb``) for these settings."""
    seed = _number("seed", s.seed, positive=False)
    if not (seed.is_integer() and 0 <= seed < 2**63):
        raise D2TurbError(f"seed must be a whole number in [0, 2^63), got {s.seed!r}")
    argv = ["simulate", input_name, "--out", out, "--seed", str(int(seed))]
    if s.strength == "D/r0":
        argv += ["--dr0", fmt_float(_number("D/r0", s.dr0))]
    elif s.strength == "Cn²":
        argv += ["--cn2", fmt_float(_number("Cn²", s.cn2))]
    else:
        raise D2TurbError(f"strength must be one of {', '.join(STRENGTHS)}, got {s.strength!r}")
    if s.depth == "upload":
        if not depth_name:
            raise D2TurbError("depth source 'upload': upload a depth map first")
        argv += ["--depth", depth_name] + (["--disparity"] if s.disparity else [])
    elif s.depth in ("none", "prior"):
        argv += ["--depth", s.depth]
    else:
        raise D2TurbError(f"depth source must be one of {', '.join(DEPTH_SOURCES)}, got {s.depth!r}")
    argv += ["--aperture", fmt_float(_number("aperture", s.aperture_m))]
    argv += ["--wavelength", *[fmt_float(w) for w in parse_wavelengths_nm(s.wavelength_nm)]]
    argv += ["--path-length", fmt_float(_number("path length", s.path_length_m))]
    if s.ifov_urad not in (None, "", 0, 0.0):
        argv += ["--ifov", fmt_float(_scaled("pixel IFOV (µrad)", s.ifov_urad, -6))]
    if s.modulation not in MODULATIONS:
        raise D2TurbError(f"modulation must be one of {', '.join(MODULATIONS)}, got {s.modulation!r}")
    offset = _number("offset s", s.offset_s, positive=False)
    argv += ["--modulation", s.modulation, "--offset", fmt_float(offset), "--save-flow"]
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
    argv = simulate_argv(s, name, depth_name)
    run_argv = [str(run / a) if a in (name, depth_name) else a for a in argv]
    run_argv[run_argv.index("--out") + 1] = str(run / "out")

    # validate everything the command will meet before running it, with the user's file names in messages
    args = parse_cli(run_argv)
    params = make_params(args, args.dr0)
    depth = depth_for_image(args.depth, run / name, image, is_disparity=args.disparity)  # refuses another aspect
    run_cli(run_argv)
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


def _video_size(path: Path) -> tuple[int, int, int]:
    """(frames, width, height) of a video from its container, without decoding it."""
    try:
        import imageio.v3 as iio
    except ImportError as exc:
        raise D2TurbError(f"{path.name}: reading video needs imageio; {VIDEO_HINT}") from exc
    plugin = "pillow" if path.suffix.lower() == ".gif" else "pyav"
    try:
        props = iio.improps(path, plugin=plugin)
    except Exception as exc:  # noqa: BLE001 - any decoder failure means "cannot read this video"
        first = (str(exc).strip().splitlines() or [exc.__class__.__name__])[0]
        raise D2TurbError(f"{path.name}: cannot read video ({first}); {VIDEO_HINT}") from exc
    frames = int(props.n_images) if props.is_batch else 1
    dims = props.shape[1:3] if props.is_batch else props.shape[0:2]
    return frames, int(dims[1]), int(dims[0])


def restore_argv(input_name: str, weights: str, tile: int, overlap: int, device: str, out: str = "out") -> list[str]:
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
        frames, w, h = _video_size(src)
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
    run_argv = [str(run / a) if a == name else a for a in argv]
    run_argv[run_argv.index("--out") + 1] = str(run / "out")
    run_cli(run_argv)
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
        frames, w, h = _video_size(run / name)
        if frames == 0:  # containers that do not store it (mkv, webm): count by decoding
            frames = sum(1 for _ in iter_video(run / name))
        if frames > limits.video_frames:
            raise D2TurbError(
                f"{src.name}: {frames} frames is more than the app takes ({limits.video_frames}); "
                "trim the video or use the command line"
            )
        check_pixels(src.name, w, h, limits.restore_pixels)
        clip, mp4 = name, f"{Path(name).stem}.mp4"
    elif src.suffix.lower() in IMAGE_SUFFIXES:
        w, h = image_size(src)
        check_pixels(src.name, w, h, limits.sim_pixels)
        sim_dr0 = dr0 or 3.0
        sim = ["simulate-video", name, "--out", "clip", "--frames", str(CLIP_SIM_FRAMES), "--dr0", f"{sim_dr0:g}"]
        sim += ["--wind", "2", "--boil", "0.1", "--no-mp4"]
        run_cli([str(run / a) if a in (name, "clip") else a for a in sim])
        commands.append(sim)
        clip, frames, mp4, dr0 = "clip/turb", CLIP_SIM_FRAMES, "turb_restored.mp4", sim_dr0
        notes.append(f"a {frames}-frame clip was simulated from the image at D/r0 = {sim_dr0:g} and restored with it")
    else:
        raise D2TurbError(f"{src.name}: not a video or image file type ({_known(IMAGE_SUFFIXES | VIDEO_SUFFIXES)})")
    argv = clip_argv(clip, temporal, dr0)
    run_argv = [str(run / a) if a in (name, clip) else a for a in argv]
    run_argv[run_argv.index("--out") + 1] = str(run / "out")
    run_cli(run_argv)
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
