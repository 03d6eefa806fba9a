"""Field-realistic clips (``make-dataset --profile field --frames N``, issue 49): a real camera's clip of a turbulent
scene, with the ground truth of every frame.

Per clip, drawn from ``(seed, index)`` alone and recorded in its meta line (``"field"``):

* **camera shake**: the camera pose of frame t, a translation (dx, dy) px and a rotation θ about the frame centre,
  is a random walk (Gaussian steps) with occasional jumps, kept within ±5 % of the frame (:func:`draw_shake`);
* **moving objects**: 1–2 rectangular patches of other clean images of the same folders crossing the scene at
  constant velocity; their box in every frame is recorded (``boxes``: [x0, y0, x1, y1], end exclusive, or null
  where the object is outside the frame);
* **the camera**: lens blur beyond diffraction, exposure, Poisson–Gaussian sensor noise, highlight clipping, the
  sRGB tone curve, in-camera sharpening, a resize, and a codec (JPEG, H.264 or H.265) (:func:`camera_pipeline`).

The scene is rendered in **linear light** (the clean sRGB images decoded by IEC 61966-2-1), the turbulence is
applied to it (light is blurred as radiance), then the camera. The ground truth of frame t is the clean scene seen
with frame t's pose and objects, at the clip's exposure (clipped at saturation) and sRGB-encoded: a restorer that
keeps frame t's geometry and removes the turbulence and the camera's degradations scores high. ``FIELD_RANGES``
holds every range (docs/datasets.md, "Field-realistic clips").
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from d2turb.data.plan import crop_box, keyed_rng
from d2turb.errors import D2TurbError
from d2turb.ops.splat import invert_flow
from d2turb.sim.camera import linear_to_srgb, optics_blur, poisson_gaussian_noise, srgb_to_linear, unsharp_mask

FIELD_RANGES = {
    "shake_step_px": [0.0, 1.5],  # σ of the walk's step per frame and axis, uniform per clip
    "shake_rot_step_deg": [0.0, 0.08],  # σ of the rotation's step per frame, uniform per clip
    "jump_rate": [0.0, 0.1],  # probability of a jump per frame, uniform per clip
    "jump_frac": 0.05,  # a jump is uniform in ±5 % of the frame side per axis
    "max_shift_frac": 0.05,  # the pose's translation is kept within ±5 % of the side (clipped)
    "max_rot_deg": 1.5,  # and its rotation within ±1.5°
    "objects": [1, 2],  # moving objects per clip, uniform
    "object_side_frac": [0.12, 0.3],  # width and height of an object, each uniform, × the frame side
    "object_speed_px": [0.5, 4.0],  # px per frame, uniform; direction uniform; centred at mid-clip in the middle 60 %
    "defocus_px": [0.0, 1.5],  # radius of the defocus disk, uniform (below 0.5: none)
    "mtf_sigma_px": [0.3, 0.9],  # σ of the Gaussian lens MTF, uniform
    "exposure": [1.0, 1.4],  # gain on the linear scene before saturation at 1, uniform
    "shot_gain": [1e-4, 2e-3],  # linear value of one photo-electron (500–10 000 e⁻ at saturation), log-uniform
    "read_sigma": [5e-4, 3e-3],  # read noise σ in linear units, log-uniform
    "sharpen_amount": [0.0, 1.2],  # unsharp mask amount, uniform
    "sharpen_sigma_px": [0.8, 2.0],  # its Gaussian σ, uniform
    "resize_prob": 0.5,  # probability that the clip was recorded smaller and scaled back up
    "resize_factor": [0.6, 0.9],  # the recorded size / the frame size, uniform (INTER_AREA down, bicubic up)
    "codecs": ["jpeg", "h264", "h265"],  # one per clip, equally likely
    "jpeg_quality": [60, 95],  # integer, uniform (OpenCV, 4:2:0)
    "video_bpp": [0.1, 0.6],  # bits per pixel and frame, log-uniform: bitrate = bpp · W · H · fps (PyAV)
}


def window_margin(patch: int) -> int:
    """Border (px) around the frame that the largest pose can bring into view (translation + rotation)."""
    shift = FIELD_RANGES["max_shift_frac"] * patch
    rot = patch / math.sqrt(2) * math.radians(FIELD_RANGES["max_rot_deg"])
    return math.ceil(shift + rot) + 3


def draw_shake(rng: np.random.Generator, frames: int, patch: int) -> dict:
    """The camera poses of a clip: ``dx_px``, ``dy_px`` (the scene's displacement in the frame, px) and ``rot_deg``
    (its rotation about the frame centre) per frame, with the drawn ``step_px``, ``rot_step_deg``, ``jump_rate`` and
    the ``jumps`` (frame indices). Frame 0 has pose 0."""
    r = FIELD_RANGES
    step = float(rng.uniform(*r["shake_step_px"]))
    rot_step = float(rng.uniform(*r["shake_rot_step_deg"]))
    rate = float(rng.uniform(*r["jump_rate"]))
    max_shift, jump = r["max_shift_frac"] * patch, r["jump_frac"] * patch
    pose = np.zeros((frames, 3))
    jumps = []
    for t in range(1, frames):
        d = pose[t - 1].copy()
        d[:2] += rng.normal(0.0, step, 2)
        d[2] += rng.normal(0.0, rot_step)
        if rng.random() < rate:
            d[:2] += rng.uniform(-jump, jump, 2)
            jumps.append(t)
        d[:2] = np.clip(d[:2], -max_shift, max_shift)
        d[2] = np.clip(d[2], -r["max_rot_deg"], r["max_rot_deg"])
        pose[t] = d
    return {
        "step_px": step,
        "rot_step_deg": rot_step,
        "jump_rate": rate,
        "jumps": jumps,
        "dx_px": pose[:, 0].round(4).tolist(),
        "dy_px": pose[:, 1].round(4).tolist(),
        "rot_deg": pose[:, 2].round(5).tolist(),
    }


def draw_objects(rng: np.random.Generator, frames: int, patch: int, n_sources: int, scene_source: int) -> list[dict]:
    """Moving objects: ``source`` (index into the sources, not the scene's), ``crop_u``/``crop_v`` (where in it),
    ``size`` [w, h] px, ``start`` [x, y] (top-left in world coordinates of frame 0's view, px) and ``velocity``
    [vx, vy] px per frame, crossing the middle of the frame at mid-clip."""
    r = FIELD_RANGES
    out = []
    for _ in range(int(rng.integers(r["objects"][0], r["objects"][1] + 1))):
        source = int(rng.integers(n_sources - 1)) if n_sources > 1 else 0
        if n_sources > 1 and source >= scene_source:
            source += 1
        w, h = (int(round(rng.uniform(*r["object_side_frac"]) * patch)) for _ in range(2))
        speed, angle = float(rng.uniform(*r["object_speed_px"])), float(rng.uniform(0, 2 * math.pi))
        v = np.array([speed * math.cos(angle), speed * math.sin(angle)])
        mid = rng.uniform(0.2, 0.8, 2) * patch  # centre at mid-clip
        start = mid - np.array([w, h]) / 2 - v * (frames - 1) / 2
        u, vv = rng.random(2)
        out.append(
            {
                "source": source,
                "crop_u": float(u),
                "crop_v": float(vv),
                "size": [w, h],
                "start": start.round(4).tolist(),
                "velocity": v.round(4).tolist(),
            }
        )
    return out


def draw_camera(rng: np.random.Generator, patch: int, fps: float) -> dict:
    """The camera of a clip (every key of ``FIELD_RANGES``' camera part, drawn)."""
    r = FIELD_RANGES

    def log_uniform(lo_hi):
        return float(math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1]))))

    cam = {
        "defocus_px": float(rng.uniform(*r["defocus_px"])),
        "mtf_sigma_px": float(rng.uniform(*r["mtf_sigma_px"])),
        "exposure": float(rng.uniform(*r["exposure"])),
        "shot_gain": log_uniform(r["shot_gain"]),
        "read_sigma": log_uniform(r["read_sigma"]),
        "sharpen_amount": float(rng.uniform(*r["sharpen_amount"])),
        "sharpen_sigma_px": float(rng.uniform(*r["sharpen_sigma_px"])),
    }
    resize = rng.random() < r["resize_prob"]
    factor = float(rng.uniform(*r["resize_factor"]))
    cam["resize_factor"] = factor if resize else 1.0
    cam["codec"] = r["codecs"][int(rng.integers(len(r["codecs"])))]
    quality = int(rng.integers(r["jpeg_quality"][0], r["jpeg_quality"][1] + 1))
    bpp = log_uniform(r["video_bpp"])
    if cam["codec"] == "jpeg":
        cam["jpeg_quality"] = quality
    else:  # the bitrate of the frames the codec sees (after the resize)
        cam["bpp"] = bpp
        cam["bitrate_bps"] = int(round(bpp * (patch * cam["resize_factor"]) ** 2 * fps))
    return cam


def draw_clip(seed: int, index: int, frames: int, patch: int, fps: float, n_sources: int, scene_source: int) -> dict:
    """Everything drawn about field clip ``index`` (shake, objects, camera, noise seed), from (seed, index) only."""
    rng = keyed_rng(seed, 4, index)
    shake = draw_shake(rng, frames, patch)
    objects = draw_objects(rng, frames, patch, n_sources, scene_source)
    camera = draw_camera(rng, patch, fps)
    noise_seed = int(np.random.SeedSequence([int(seed), 5, int(index)]).generate_state(1, np.uint64)[0] >> 1)
    return {"shake": shake, "objects": objects, "camera": camera, "noise_seed": noise_seed}


# ---- rendering ------------------------------------------------------------------------------------------------------
def _view_matrix(dx: float, dy: float, rot_deg: float, patch: int, offset: tuple[float, float]) -> np.ndarray:
    """2×3 affine map from frame pixel coordinates to the coordinates of a layer whose frame-0 origin sits at
    ``offset`` (x, y) in the frame: x_layer = R(−θ)(x − c − d) + c − offset (a point of the world appears at
    R(θ)(p − c) + c + d)."""
    c = (patch - 1) / 2
    t = math.radians(rot_deg)
    cos, sin = math.cos(t), math.sin(t)
    rinv = np.array([[cos, sin], [-sin, cos]])
    b = -rinv @ np.array([c + dx, c + dy]) + np.array([c, c]) - np.asarray(offset, dtype=np.float64)
    return np.concatenate([rinv, b[:, None]], 1)


def frame_point(x: float, y: float, dx: float, dy: float, rot_deg: float, patch: int) -> tuple[float, float]:
    """Where the world point (x, y) (frame-0 view coordinates) appears in a frame of pose (dx, dy, θ)."""
    c = (patch - 1) / 2
    t = math.radians(rot_deg)
    px, py = x - c, y - c
    return (
        math.cos(t) * px - math.sin(t) * py + c + dx,
        math.sin(t) * px + math.cos(t) * py + c + dy,
    )


def _warp(layer: np.ndarray, m: np.ndarray, patch: int, flags: int, border: int) -> np.ndarray:
    out = cv2.warpAffine(layer, m, (patch, patch), flags=flags | cv2.WARP_INVERSE_MAP, borderMode=border, borderValue=0)
    return out if out.ndim == 3 else out[..., None]


def object_box(obj: dict, t: int, pose: tuple[float, float, float], patch: int) -> list[int] | None:
    """The object's box in frame t: [x0, y0, x1, y1] (end exclusive, integer pixels that hold any of it), or None
    where none of it is in the frame."""
    w, h = obj["size"]
    x0 = obj["start"][0] + obj["velocity"][0] * t
    y0 = obj["start"][1] + obj["velocity"][1] * t
    # pixel centres at integer coordinates: the patch's pixels span [x0 − 0.5, x0 + w − 0.5]
    corners = [frame_point(x, y, *pose, patch) for x in (x0 - 0.5, x0 + w - 0.5) for y in (y0 - 0.5, y0 + h - 0.5)]
    xs, ys = [p[0] for p in corners], [p[1] for p in corners]
    # a pixel i covers [i − 0.5, i + 0.5]: the box holds every pixel touched (+1 px for the interpolation's reach)
    bx0, by0 = max(0, math.floor(min(xs) + 0.5) - 1), max(0, math.floor(min(ys) + 0.5) - 1)
    bx1, by1 = min(patch, math.ceil(max(xs) + 0.5) + 1), min(patch, math.ceil(max(ys) + 0.5) + 1)
    if bx1 <= bx0 or by1 <= by0:
        return None
    return [int(bx0), int(by0), int(bx1), int(by1)]


def render_scene(
    window: np.ndarray,
    objects: list[tuple[dict, np.ndarray]],
    shake: dict,
    patch: int,
    depth_window: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None, list[list]]:
    """The clean frames of a shaken camera looking at a scene crossed by objects.

    Args:
        window: (P + 2m, P + 2m, 3) float32 scene around the frame (m = :func:`window_margin`), any units (linear).
        objects: (drawn object, its (h, w, 3) float32 patch) pairs, painted over the scene in that order.
        shake: :func:`draw_shake`'s poses.
        depth_window: (P + 2m, P + 2m) depth around the frame, moved with the camera (objects take the scene's).
    Returns:
        frames (N, P, P, 3) float32, depth (N, P, P) or None, boxes (per object, per frame: list or None).
    Shape: the frame-0 view is the window's central P × P.
    """
    m = (window.shape[0] - patch) // 2
    n = len(shake["dx_px"])
    frames = np.empty((n, patch, patch, 3), np.float32)
    depth = None if depth_window is None else np.empty((n, patch, patch), np.float32)
    boxes: list[list] = [[] for _ in objects]
    for t in range(n):
        pose = (shake["dx_px"][t], shake["dy_px"][t], shake["rot_deg"][t])
        view = _view_matrix(*pose, patch, (-m, -m))
        frame = _warp(window, view, patch, cv2.INTER_CUBIC, cv2.BORDER_REFLECT)
        if depth is not None:
            depth[t] = _warp(depth_window, view, patch, cv2.INTER_LINEAR, cv2.BORDER_REFLECT)[..., 0]
        for k, (obj, pixels) in enumerate(objects):
            origin = (obj["start"][0] + obj["velocity"][0] * t, obj["start"][1] + obj["velocity"][1] * t)
            to_obj = _view_matrix(*pose, patch, origin)
            paint = _warp(pixels, to_obj, patch, cv2.INTER_CUBIC, cv2.BORDER_REPLICATE)
            alpha = _warp(np.ones(pixels.shape[:2], np.float32), to_obj, patch, cv2.INTER_LINEAR, cv2.BORDER_CONSTANT)
            frame = frame * (1 - alpha) + paint * alpha
            boxes[k].append(object_box(obj, t, pose, patch))
        frames[t] = np.clip(frame, 0, None)
    return frames, depth, boxes


# ---- the camera -----------------------------------------------------------------------------------------------------
def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 255), 0, 255).astype(np.uint8)


def jpeg_round_trip(frames_u8: np.ndarray, quality: int) -> np.ndarray:
    """(N, H, W, 3) uint8 RGB frames through OpenCV's JPEG at ``quality`` and back."""
    out = np.empty_like(frames_u8)
    for i, f in enumerate(frames_u8):
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(f[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        if not ok:
            raise D2TurbError("JPEG encoding failed")
        out[i] = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return out


def camera_pipeline(linear: torch.Tensor, cam: dict, noise_seed: int, fps: float = 30.0) -> np.ndarray:
    """A camera's clip of linear radiance: lens blur, exposure, Poisson–Gaussian noise, clipping at saturation, sRGB
    tone curve, unsharp mask, 8 bits, resize, codec.

    Args:
        linear: (N, 3, H, W) linear radiance in [0, 1] (the turbulent frames).
        cam: :func:`draw_camera`'s settings; noise_seed: of the sensor noise.
    Returns:
        (N, H, W, 3) uint8 frames as the camera (and codec) deliver them.
    """
    gen = torch.Generator().manual_seed(int(noise_seed))
    x = optics_blur(linear.float(), cam["defocus_px"], cam["mtf_sigma_px"])
    x = poisson_gaussian_noise(x.clamp_min(0) * cam["exposure"], cam["shot_gain"], cam["read_sigma"], gen)
    x = linear_to_srgb(x.clamp(0, 1))
    x = unsharp_mask(x, cam["sharpen_amount"], cam["sharpen_sigma_px"])
    u8 = _to_u8(x.permute(0, 2, 3, 1).numpy())
    n, h, w = u8.shape[:3]
    if cam["resize_factor"] < 1:
        size = (max(2, round(w * cam["resize_factor"])), max(2, round(h * cam["resize_factor"])))
        small = np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in u8])
        small = coded(small, cam, fps)  # the camera records the small frames; the viewer scales them up
        return np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_CUBIC) for f in small])
    return coded(u8, cam, fps)


def coded(frames_u8: np.ndarray, cam: dict, fps: float) -> np.ndarray:
    """The codec of ``cam`` (``jpeg`` at ``jpeg_quality``, ``h264``/``h265`` at ``bitrate_bps``) on (N, H, W, 3)
    uint8 frames."""
    from d2turb.video_codec import encode_decode  # PyAV is the video extra: needed only when a clip is encoded

    if cam["codec"] == "jpeg":
        return jpeg_round_trip(frames_u8, cam["jpeg_quality"])
    return encode_decode(frames_u8, cam["codec"], cam["bitrate_bps"], fps)


def clean_frames(linear: np.ndarray, exposure: float) -> np.ndarray:
    """The ground truth of linear clean frames (N, H, W, 3): exposed, clipped at saturation, sRGB-encoded, 8 bits."""
    x = torch.from_numpy(np.clip(linear * exposure, 0, 1))
    return _to_u8(linear_to_srgb(x).numpy())


def decode_source(image: torch.Tensor) -> np.ndarray:
    """A clean sRGB image (3, H, W) in [0, 1] → (H, W, 3) float32 linear radiance."""
    return srgb_to_linear(image.float()).permute(1, 2, 0).numpy().astype(np.float32)


# ---- a chunk of make-dataset ----------------------------------------------------------------------------------------
def simulate_field_chunk(sim, scenes: list[dict], dr0: torch.Tensor, generator, frames: int, settings: dict, device):
    """Turbulence on the rendered linear frames of a chunk of field clips, then each clip's camera.

    Args:
        scenes: per clip, ``frames_lin`` (N, P, P, 3) float32 linear, ``depth`` (N, P, P) or None, ``draw``
            (:func:`draw_clip`).
        dr0: (B,) D/r0; generator: the chunk's simulator generator; settings: the sequence settings.
    Returns:
        per clip, dict(turb, tilt, gt: (3, N·P, P) float32 filmstrips in [0, 1]; bwd_flow_px (N, 2, P, P)).
    """

    lin = [torch.from_numpy(s["frames_lin"]).permute(0, 3, 1, 2).clamp(0, 1) for s in scenes]  # (N, 3, P, P)
    with_depth = scenes[0]["depth"] is not None
    depth = [torch.from_numpy(s["depth"])[:, None] for s in scenes] if with_depth else None

    def frame_stack(t):
        return torch.stack([x[t] for x in lin]).to(device)

    images = (frame_stack(t) for t in range(frames))
    depths = (torch.stack([d[t] for d in depth]).to(device) for t in range(frames)) if with_depth else None
    turb, tilt, bwd_flow_px = [], [], []
    for res in sim.sequence(images, frames=frames, depth=depths, dr0=dr0, generator=generator, **settings):
        turb.append(res.turb.float().cpu())
        tilt.append(res.tilt.float().cpu())
        bwd_flow_px.append(invert_flow(res.fwd_flow_px).float().cpu())
    turb_t, tilt_t = torch.stack(turb, 1), torch.stack(tilt, 1)  # (B, N, ...)
    bwd_flow_px_t = torch.stack(bwd_flow_px, 1)
    out = []
    for b, scene in enumerate(scenes):
        cam, fps = scene["draw"]["camera"], float(settings.get("fps", 30.0))
        if not torch.isfinite(turb_t[b]).all():
            raise D2TurbError("simulator produced NaN/inf")
        coded_u8 = camera_pipeline(turb_t[b], cam, scene["draw"]["noise_seed"], fps)
        tilt_u8 = clean_frames(tilt_t[b].permute(0, 2, 3, 1).numpy(), cam["exposure"])
        gt_u8 = clean_frames(scene["frames_lin"], cam["exposure"])

        def strip(u8):
            return torch.from_numpy(np.ascontiguousarray(u8.reshape(-1, *u8.shape[2:]))).permute(2, 0, 1).float() / 255

        out.append(
            {"turb": strip(coded_u8), "tilt": strip(tilt_u8), "gt": strip(gt_u8), "bwd_flow_px": bwd_flow_px_t[b]}
        )
    return out


def prepare_scene(plan, cfg, image: torch.Tensor, dmap, object_cache, n_sources: int, scene_source: int) -> dict:
    """Render one field clip's clean linear frames from its (resized) source image and depth.

    Returns dict(frames_lin, depth, draw, window [x0, y0, x1, y1], boxes)."""

    p, n = cfg.patch, cfg.frames
    m = window_margin(p)
    x0, y0, x1, y1 = crop_box(plan, image.shape[-2], image.shape[-1], p + 2 * m)
    window = decode_source(image[:, y0:y1, x0:x1])
    depth_window = None if dmap is None else dmap[0, y0:y1, x0:x1].float().numpy()
    draw = draw_clip(cfg.seed, plan.index, n, p, float(cfg.sequence.get("fps", 30.0)), n_sources, scene_source)
    objects = []
    for obj in draw["objects"]:
        k, img, _ = object_cache.get(obj["source"])
        obj["source_path"] = str(object_cache.sources[k])
        w, h = obj["size"]
        oh, ow = img.shape[-2:]
        ox = min(int(obj["crop_u"] * (ow - w + 1)), ow - w)
        oy = min(int(obj["crop_v"] * (oh - h + 1)), oh - h)
        objects.append((obj, decode_source(img[:, oy : oy + h, ox : ox + w])))
    frames_lin, depth, boxes = render_scene(window, objects, draw["shake"], p, depth_window)
    for (obj, _), b in zip(objects, boxes):
        obj["boxes"] = b
    return {"frames_lin": frames_lin, "depth": depth, "draw": draw, "window": [x0, y0, x1, y1]}
