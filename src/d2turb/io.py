"""Image and file I/O: robust reading of odd images, atomic writes (temp name, then rename) with the mode a
normal write gets, output-folder checks, and a background writer for batch commands."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import queue
import re
import secrets
import stat
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterable, Iterator
from io import BytesIO
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError

from d2turb.defaults import DEFAULT_MAX_PIXELS, DEFAULT_PNG_LEVEL
from d2turb.device import usable_cores
from d2turb.errors import D2TurbError

try:  # a dependency; a checkout run without installing it (the GPU machines' image) writes PNG with Pillow
    import imagecodecs
except ImportError:
    imagecodecs = None

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm"}
_limits = {"max_pixels": DEFAULT_MAX_PIXELS}


def cache_dir(*parts: str) -> Path:
    """The user's folder of local weights: ``$D2TURB_CACHE_DIR`` (default ``~/.cache/d2turb``) / parts."""
    return Path(os.environ.get("D2TURB_CACHE_DIR", Path.home() / ".cache" / "d2turb")).expanduser().joinpath(*parts)


def list_images(folder: str | os.PathLike, recursive: bool = False) -> list[Path]:
    """Image files directly inside ``folder`` (with ``recursive``, also in its sub-folders), sorted by path.
    Hidden files and folders (names starting with a dot: our temp files, macOS ``._`` files) are skipped."""
    folder = Path(folder)
    if not folder.is_dir():
        raise D2TurbError(f"{folder}: not a directory")
    try:
        entries = list(folder.rglob("*") if recursive else folder.iterdir())
    except OSError as exc:
        raise D2TurbError(f"{folder}: cannot read folder ({_reason(exc)})") from exc
    found = []
    for p in entries:
        hidden = any(part.startswith(".") for part in p.relative_to(folder).parts)
        # a dangling or looping symbolic link is kept: reading it reports it, like any unreadable file
        if not hidden and p.suffix.lower() in IMAGE_SUFFIXES and (p.is_file() or _broken_link(p)):
            found.append(p)
    return sorted(found, key=lambda p: p.relative_to(folder).parts)


def _broken_link(path: Path) -> bool:
    return path.is_symlink() and not path.exists()


def _missing_reason(path: Path) -> str:
    """Why ``path`` is no readable file: a dangling or looping symbolic link, or absent."""
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                return f"{path}: cannot read image (symbolic link loop)"
            return f"{path}: cannot read image (dangling symbolic link to {os.readlink(path)})"
    if path.is_dir():
        return f"{path}: is a folder, not an image file"
    return f"{path}: no such file"


def expand_inputs(inputs: list[str]) -> list[Path]:
    """Files and folders of images on the command line → list of image files."""
    paths: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            paths.extend(list_images(p))
        elif p.is_file():
            paths.append(p)
        else:
            raise D2TurbError(_missing_reason(p) if p.is_symlink() else f"{p}: no such file or directory")
    if not paths:
        raise D2TurbError("no input images found")
    return paths


FLOAT_TOLERANCE = 1e-3  # float pixels this far outside [0, 1] (rounding of an earlier computation) are clipped


def _to_float_array(img: Image.Image, path: Path | str = "image") -> np.ndarray:
    """PIL image of any mode → float32 HxWx3 RGB in [0, 1] (alpha dropped, grey replicated).

    Integer images are scaled by their type's maximum (16-bit: 65535; 32-bit: 65535 when a value exceeds 255).
    Float images (TIFF ``F``) must hold finite values in [0, 1]: NaN/inf, or values beyond [0, 1] by more than
    :data:`FLOAT_TOLERANCE` (radiance, a 0-255 or 0-1000 scale), are refused naming the range found, rather than
    clipped into a saturated image."""
    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        lo, hi = float(arr.min(initial=0)), float(arr.max(initial=0))
        if lo < 0 or hi > 65535:
            raise D2TurbError(
                f"{path}: 32-bit integer pixels span {lo:g} to {hi:g}, outside 0-65535; save the image as 8- or 16-bit"
            )
        scale = 65535.0 if hi > 255 or mode.startswith("I;16") else 255.0
        arr = (arr / scale)[..., None].repeat(3, axis=2)
    elif mode == "F":
        arr = np.asarray(img, dtype=np.float64)
        if not np.isfinite(arr).all():
            raise D2TurbError(f"{path}: image contains NaN or infinite values")
        lo, hi = float(arr.min(initial=0)), float(arr.max(initial=0))
        if lo < -FLOAT_TOLERANCE or hi > 1 + FLOAT_TOLERANCE:
            raise D2TurbError(
                f"{path}: floating-point pixels span {lo:g} to {hi:g}, outside [0, 1]; rescale the image to [0, 1] "
                "(or save it as 8- or 16-bit)"
            )
        arr = arr[..., None].repeat(3, axis=2)
    else:
        if mode not in ("RGB", "L"):
            img = img.convert("RGBA").convert("RGB") if "A" in mode or mode == "P" else img.convert("RGB")
        arr = np.asarray(img.convert("RGB"), dtype=np.float64) / 255.0
    return np.clip(arr, 0.0, 1.0).astype(np.float32)


def set_max_pixels(limit: int | None) -> None:
    """Largest image (width × height) that :func:`read_image` decodes; None or 0 = no limit.

    Bigger headers are refused before decoding (decompression bombs: a tiny file claiming 100000²
    pixels). The CLI sets it from ``--max-pixels``; the default is Pillow's own limit.
    """
    if limit is not None and limit < 0:
        raise D2TurbError(f"--max-pixels must be >= 0 (0 = no limit), got {limit}")
    _limits["max_pixels"] = limit or None


def open_image(path: str | os.PathLike, max_pixels: int | None = -1) -> Image.Image:
    """Decode an image file with Pillow (EXIF orientation applied), refusing oversized headers.

    Args:
        path: image file.
        max_pixels: pixel limit; -1 (default) = the limit of :func:`set_max_pixels`, None = no limit.

    Returns:
        The loaded PIL image (its file closed).

    Raises:
        D2TurbError: missing, unreadable or corrupt file, or a header larger than the limit.
    """
    path = Path(path)
    if not path.is_file():
        raise D2TurbError(_missing_reason(path))
    limit = _limits["max_pixels"] if max_pixels == -1 else max_pixels
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # the limit is applied below, with a message that names the file
    try:
        with Image.open(path) as img:
            w, h = img.size
            if limit and w * h > limit:
                raise D2TurbError(
                    f"{path}: image claims {w}x{h} pixels ({w * h / 1e6:.0f} megapixels), over the limit of "
                    f"{limit / 1e6:.0f} megapixels (decompression-bomb guard); allow it with --max-pixels {w * h}"
                )
            img.load()
            return ImageOps.exif_transpose(img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) from an image file's header, without decoding it (EXIF orientation not applied)."""
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # only the header is read
    try:
        with Image.open(path) as img:
            return img.size
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    finally:
        Image.MAX_IMAGE_PIXELS = saved


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_ORIENTATION_KEYS = (b"eXIf", b"Raw profile type exif", b"XML:com.adobe.xmp")  # where Pillow looks for one


def _read_plain_png(path: Path) -> np.ndarray | None:
    """HxWx3 uint8 pixels of an 8-bit RGB PNG (at least 2x2, within the pixel limit) decoded by libpng, a third
    faster than Pillow; None for any other file, or one that may hold an EXIF orientation (any chunk that
    Pillow reads one from: such files take Pillow's path, which applies it), or one libpng refuses."""
    if imagecodecs is None or path.suffix.lower() != ".png":
        return None
    try:
        data = path.read_bytes()
    except OSError:
        return None
    # signature, IHDR's length and type, width, height, 8 bits, RGB, standard compression and filters, no interlace
    if data[:16] != _PNG_SIGNATURE + b"\x00\x00\x00\x0dIHDR" or data[24:29] != b"\x08\x02\x00\x00\x00":
        return None
    w, h = struct.unpack(">II", data[16:24])
    limit = _limits["max_pixels"]
    if min(w, h) < 2 or (limit and w * h > limit) or any(key in data for key in _PNG_ORIENTATION_KEYS):
        return None
    try:
        pixels = imagecodecs.png_decode(data)
    except Exception:  # Pillow's path reports it
        return None
    return pixels if pixels.shape == (h, w, 3) and pixels.dtype == np.uint8 else None


def read_image(path: str | os.PathLike) -> torch.Tensor:
    """Read an image as a float32 tensor (3, H, W) in [0, 1].

    Grayscale is replicated to RGB, alpha is dropped, 16-bit is scaled by 65535, palette images are
    expanded and EXIF orientation is applied. Corrupt or unreadable files, and headers over the pixel
    limit (:func:`set_max_pixels`), raise ``D2TurbError``.
    """
    path = Path(path)
    pixels = _read_plain_png(path)
    if pixels is None:
        img = open_image(path)
        if img.mode == "RGB" and min(img.size) >= 2:
            pixels = np.asarray(img)
    if pixels is not None:  # the common case, in float32 (x/255 rounds as in float64); numpy: see float_array
        arr = pixels.transpose(2, 0, 1).astype(np.float32, order="C")
        arr /= np.float32(255.0)
        return torch.from_numpy(arr)
    try:
        arr = _to_float_array(img, path)
    except (OSError, ValueError) as exc:
        raise D2TurbError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise D2TurbError(f"{path}: image is too small ({arr.shape[1]}x{arr.shape[0]})")
    if not np.isfinite(arr).all():
        raise D2TurbError(f"{path}: image contains NaN or infinite values")
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1)))


def check_image_tensor(x: torch.Tensor, name: str = "image", channels: int | None = None) -> None:
    """Validate a (B, C, H, W) floating tensor without NaN/inf."""
    if not isinstance(x, torch.Tensor):
        raise D2TurbError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4:
        raise D2TurbError(f"{name}: expected shape (B, C, H, W), got {tuple(x.shape)}")
    if channels is not None and x.shape[1] != channels:
        raise D2TurbError(f"{name}: expected {channels} channels, got {x.shape[1]}")
    if not x.is_floating_point():
        raise D2TurbError(f"{name}: expected a floating tensor, got {x.dtype}")
    if not torch.isfinite(x).all():
        raise D2TurbError(f"{name}: contains NaN or infinite values")


# ------------------------------------------------------------------------------------------------ writing
_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<token>[A-Za-z0-9_-]+)\.tmp(?P<suffix>\.[^.]+)?$")


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc) or exc.__class__.__name__


NAME_MAX = 255  # bytes in one file name (Linux, macOS, Windows)


def temp_name(name: str, token: str) -> str:
    """``.NAME.<token>.tmpSUFFIX``, with NAME's stem cut (at a character boundary, its suffix kept) so that the
    temp name fits in :data:`NAME_MAX` bytes whenever ``name`` does; :func:`remove_stale_temp_files` reads both."""
    suffix = Path(name).suffix
    tail = f".{token}.tmp{suffix}"
    if len(f".{name}{tail}".encode()) > NAME_MAX:
        stem = name[: len(name) - len(suffix)]
        room = NAME_MAX - len(f".{suffix}{tail}".encode())
        name = stem.encode()[: max(room, 1)].decode(errors="ignore") + suffix
    return f".{name}{tail}"


def _open_temp(path: Path) -> tuple[Path, int]:
    """A new temp file next to ``path``, ``.NAME.<pid>-<random>.tmpSUFFIX`` (:func:`temp_name`), open for writing.
    Created with mode 0666, so the kernel applies the umask exactly as for a normal write (mkstemp: 0600)."""
    for _ in range(100):
        tmp = path.with_name(temp_name(path.name, f"{os.getpid()}-{secrets.token_hex(4)}"))
        try:
            return tmp, os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name next to {path}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    The file gets the mode a normal write would (0666 minus the umask). Failures to create, write or rename
    (a full disk, a read-only folder, a parent that is a file) raise ``D2TurbError`` naming ``path``; the
    temporary file never survives an exception. A SIGKILL can leave it: :func:`remove_stale_temp_files`.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp, fd = _open_temp(path)
        os.close(fd)
        mode = stat.S_IMODE(tmp.stat().st_mode)  # 0666 minus the umask, as the kernel applied it
    except OSError as exc:
        raise D2TurbError(f"cannot write {path}: {_reason(exc)}") from exc
    try:
        yield tmp
        if stat.S_IMODE(tmp.stat().st_mode) != mode:  # a writer that replaced the file (safetensors: 0600)
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except OSError as exc:
        raise D2TurbError(f"cannot write {path}: {_reason(exc)}") from exc
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, as :func:`atomic_path` does, in four system calls (the batch
    commands write a few small files per image)."""
    path = Path(path)
    try:
        try:
            tmp, fd = _open_temp(path)
        except FileNotFoundError:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp, fd = _open_temp(path)
    except OSError as exc:
        raise D2TurbError(f"cannot write {path}: {_reason(exc)}") from exc
    try:
        with open(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise D2TurbError(f"cannot write {path}: {_reason(exc)}") from exc
        raise


def _owner_is_gone(token: str, mtime: float) -> bool:
    """Whether the process that made a temp file (pid in its name) no longer runs. Names without a pid
    (older versions) are always stale."""
    m = re.fullmatch(r"(\d+)-[0-9a-f]+", token)
    if m is None:
        return True
    pid = int(m.group(1))
    if pid == os.getpid():
        return False
    if os.name != "posix":  # no cheap liveness probe: an hour without change means abandoned
        return time.time() - mtime > 3600
    return not _pid_alive(pid)


def remove_stale_temp_files(folder: str | os.PathLike, recursive: bool = False) -> int:
    """Delete the temporary files :func:`atomic_path` left in ``folder`` (with ``recursive``, in its sub-folders
    too) when its process was killed; files of processes that still run are kept. Returns how many were removed."""
    folder = Path(folder)
    count = 0
    if not folder.is_dir():
        return 0
    for p in folder.rglob(".*.tmp*") if recursive else folder.iterdir():
        m = _TEMP_RE.match(p.name)
        if m is None or (m.group("suffix") or "") != Path(m.group("name")).suffix:
            continue
        try:
            if p.is_file() and _owner_is_gone(m.group("token"), p.stat().st_mtime):
                p.unlink()
                count += 1
        except OSError:
            continue
    return count


def _same_folder(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


LOCK_NAME = ".d2turb.lock"


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    if os.name != "posix":
        return True  # no cheap probe: never take over
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: alive, another user's
        return True
    return True


class FolderLock:
    """Exclusive use of a folder by one run: ``FOLDER/.d2turb.lock`` holds the owner's pid, host and command.

    Taken with an atomic create (a hard link of a complete temp file; O_EXCL where links are not supported); a
    lock whose process no longer runs on this host (a killed run) is taken over; one held by a live process is a
    one-line ``D2TurbError`` naming it. Released (the file removed) by :meth:`release` or on leaving the ``with``
    block, only if it is still ours."""

    def __init__(self, folder: str | os.PathLike, command: str):
        self.folder, self.command = Path(folder), command
        self.path = self.folder / LOCK_NAME
        self.token = f"{os.getpid()}-{secrets.token_hex(8)}"
        self.held = False

    def _owner(self) -> dict | None:
        """The lock's record, {} when it is unreadable or garbled, None when there is no lock."""
        try:
            record = json.loads(self.path.read_bytes())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}
        return record if isinstance(record, dict) else {}

    def _create(self) -> bool:
        data = json.dumps(
            {
                "pid": os.getpid(),
                "host": _hostname(),
                "command": self.command,
                "token": self.token,
                "since": time.time(),
            }
        ).encode()
        tmp, fd = _open_temp(self.path)
        try:
            with open(fd, "wb") as f:
                f.write(data)
            try:
                os.link(tmp, self.path)
                return True
            except FileExistsError:
                return False
            except OSError:  # no hard links on this file system
                try:
                    fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
                except FileExistsError:
                    return False
                with open(fd, "wb") as f:
                    f.write(data)
                return True
        finally:
            with contextlib.suppress(OSError):
                os.unlink(tmp)

    def acquire(self) -> FolderLock:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            for _ in range(20):
                if self._create():
                    self.held = True
                    return self
                owner = self._owner()
                if owner is None:  # released meanwhile
                    continue
                pid, host = owner.get("pid"), owner.get("host")
                if isinstance(pid, int) and (host != _hostname() or _pid_alive(pid)):
                    where = "" if host == _hostname() else f" on host {host}"
                    raise D2TurbError(
                        f"{self.folder} is in use by another {owner.get('command', 'd2turb')} run (process {pid}"
                        f"{where}); wait for it to finish, or use another folder (if that process is gone, "
                        f"remove {self.path})"
                    )
                # a dead process's lock (or a garbled one): take it over, unless another run did just now
                stale = self.path.with_name(f"{LOCK_NAME}.{self.token}.stale")
                try:
                    os.rename(self.path, stale)
                except FileNotFoundError:
                    continue
                try:
                    taken = json.loads(stale.read_bytes())
                except (OSError, ValueError):
                    taken = {}
                if taken != owner and isinstance(taken, dict) and taken:  # a run that took it over meanwhile
                    with contextlib.suppress(OSError):
                        os.link(stale, self.path)  # give it back
                os.unlink(stale)
        except OSError as exc:
            raise D2TurbError(f"cannot lock {self.folder}: {_reason(exc)}") from exc
        raise D2TurbError(f"cannot lock {self.folder}: the lock file {self.path} keeps changing")

    def release(self) -> None:
        if self.held and (self._owner() or {}).get("token") == self.token:
            with contextlib.suppress(OSError):
                self.path.unlink()
        self.held = False

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _hostname() -> str:
    import socket

    return socket.gethostname()


def check_output_dir(path: str | os.PathLike, option: str = "--out", inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Check that ``path`` is, or can be created as, a writable folder, without creating it; remove stale
    temporary files of ours inside it. Raises ``D2TurbError`` in one line otherwise.

    ``inputs``: the command's input files, for commands whose per-input outputs are named after the input
    (``NAME_turb.png``): a folder holding one of them is refused, since outputs there could replace the user's
    own files of those names (outputs never replace a file the run did not create)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise D2TurbError(f"{option} {path}: exists and is not a folder")
    if path.is_dir():
        for parent in dict.fromkeys(Path(p).parent for p in inputs):
            if _same_folder(parent, path):
                raise D2TurbError(
                    f"{option} {path}: is the folder of the input files; outputs written there could replace "
                    "files of yours with the same names, choose another output folder"
                )
    probe = path
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise D2TurbError(f"{option} {path}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise D2TurbError(f"{option} {path}: {probe} is not writable (permission denied)")
    remove_stale_temp_files(path)
    return path


def check_unique_stems(paths: Iterable[str | os.PathLike]) -> None:
    """Per-input outputs are named by the input's stem: refuse inputs that would write the same names
    (``a.png a.jpg``; compared case-insensitively, as some file systems do)."""
    seen: dict[str, list[str]] = {}
    for p in paths:
        seen.setdefault(Path(p).stem.casefold(), []).append(str(p))
    clash = [names for names in seen.values() if len(names) > 1]
    if clash:
        listed = "; ".join(", ".join(names) for names in clash[:3]) + ("; ..." if len(clash) > 3 else "")
        raise D2TurbError(f"several inputs would write the same output names ({listed}); rename or process apart")


def float_array(tensor: torch.Tensor) -> np.ndarray:
    """A tensor's values as a float32 numpy array, through no torch operator when it already is float32 on
    the CPU (writer threads: a torch operator there starts an OpenMP team of its own, and more OpenMP threads
    than cores slow the main computation's parallel regions)."""
    tensor = tensor.detach().cpu()
    return (tensor if tensor.dtype == torch.float32 else tensor.float()).numpy()


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """(3|1, H, W) or (H, W) float tensor in [0, 1] → C-contiguous HxWx3 (or HxW) uint8 array, rounded to nearest.

    One temporary (a fresh large one per call costs more in page faults than the arithmetic)."""
    arr = float_array(image) * np.float32(255.0)
    np.clip(arr, 0, 255, out=arr)
    np.rint(arr, out=arr)
    if arr.ndim == 3:
        if arr.shape[0] == 1:
            return arr[0].astype(np.uint8)
        out = np.empty(arr.shape[1:] + arr.shape[:1], np.uint8)
        np.copyto(out, arr.transpose(1, 2, 0), casting="unsafe")
        return out
    return arr.astype(np.uint8)


def _png_chunk(kind: bytes, data) -> bytes:
    return struct.pack(">I", len(data)) + kind + bytes(data) + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def _encode_png_up(array: np.ndarray, level: int) -> bytes:
    """PNG (spec: w3.org/TR/png-3) with every row filtered by "Up" (bytes minus those of the row above, mod
    256) and deflated by libdeflate: at level 1, half the time of libpng's fastest settings, files ~10 % larger."""
    h, w = array.shape[:2]
    colour = {1: 0, 2: 4, 3: 2, 4: 6}[1 if array.ndim == 2 else array.shape[2]]  # grey, +alpha, RGB, RGBA
    depth = 16 if array.dtype == np.uint16 else 8
    rows = np.ascontiguousarray(array, dtype=">u2" if depth == 16 else np.uint8).view(np.uint8).reshape(h, -1)
    filtered = np.empty((h, 1 + rows.shape[1]), np.uint8)  # big-endian samples, for 16 bits
    filtered[:, 0] = 2  # filter type: Up
    filtered[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])
    stream = memoryview(imagecodecs.deflate_encode(filtered, level=level))  # zlib format
    idat = b"".join(_png_chunk(b"IDAT", stream[i : i + (1 << 30)]) for i in range(0, len(stream), 1 << 30))
    header = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0)
    return _PNG_SIGNATURE + _png_chunk(b"IHDR", header) + idat + _png_chunk(b"IEND", b"")


def encode_png(array: np.ndarray, level: int = DEFAULT_PNG_LEVEL) -> bytes:
    """(H, W) or (H, W, 1|2|3|4) uint8 or uint16 array → PNG bytes (GIL released while compressing).

    Level 1 (the default, for speed) filters every row with "Up" and compresses with libdeflate: 1.2 ms per
    simulated 256² RGB output instead of 2.2 ms with libpng's fastest settings (Paeth, run-length zlib), files
    ~10 % larger (~13 % above level 6). Other levels: libpng's adaptive filters and zlib at that level, both
    through imagecodecs; without imagecodecs, Pillow's encoder (run-length zlib at level 1).
    """
    if not 0 <= level <= 9:
        raise D2TurbError(f"PNG level must be 0-9, got {level}")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if array.size == 0 or array.ndim not in (2, 3) or (array.ndim == 3 and not 2 <= array.shape[2] <= 4):
        raise D2TurbError(f"cannot write an image of shape {tuple(array.shape)} as PNG")
    if imagecodecs is None:
        buffer = BytesIO()
        options = {"compress_type": zlib.Z_RLE} if level == 1 else {}
        Image.fromarray(np.ascontiguousarray(array)).save(buffer, format="PNG", compress_level=level, **options)
        return buffer.getvalue()
    if level == 1 and imagecodecs.DEFLATE.available:
        return _encode_png_up(array, level)
    return imagecodecs.png_encode(np.ascontiguousarray(array), level=level)


def write_image(path: str | os.PathLike, image: torch.Tensor | np.ndarray, png_level: int = DEFAULT_PNG_LEVEL) -> None:
    """Write a (C, H, W) float tensor in [0, 1] (or an HxW[x3] uint8 array, or for PNG an HxW uint16 one) as an
    image, atomically, in the format of the path's suffix (PNG when unknown). ``png_level``: zlib level 0-9 for
    PNG (default 1: fast; 9: smallest files)."""
    if isinstance(image, torch.Tensor):
        if image.ndim == 4:
            if image.shape[0] != 1:
                raise D2TurbError(f"write_image: expected one image, got a batch of {image.shape[0]}")
            image = image[0]
        image = to_uint8(image)
    path = Path(path)
    fmt = Image.registered_extensions().get(path.suffix.lower(), "PNG")
    if fmt == "PNG":
        write_bytes(path, encode_png(image, png_level))
        return
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format=fmt)


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def write_json(path: str | os.PathLike, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode())


class BackgroundWriter:
    """Run write jobs in background threads, so a batch command reads and computes while earlier outputs
    are encoded and written. Jobs should write atomically (``write_image`` etc.) and convert tensors with
    numpy (:func:`float_array`): a torch operator in another thread starts an OpenMP team of its own.

    ``submit`` blocks while ``max_pending`` jobs wait (bounded memory). The first error of a job is raised
    in the caller at the next ``submit`` or at ``close``; later jobs are dropped. Used as a context manager,
    an exception in the block (Ctrl-C) drops the jobs not started and waits for the running ones.

    The writes are *phased* when the computation runs on the CPU with a torch thread on every core: then
    :meth:`before_compute` waits for the queued jobs, which meanwhile run one thread per core, because the
    computation's OpenMP threads lose more time to a writer beside them (spinning at barriers while it holds
    a core) than the writes take on all cores in between (benchmarks/bench_cli_sim.py). The next inputs are
    still read while the writers work. Otherwise (a GPU, or a core left free) the writes overlap.

    Args:
        max_pending: queue length.
        compute_device: device of the computation the writes alternate with (None: no computation).
        threads: writer threads (the PNG encoders release the GIL); default: one per core when phased, else
            one per two cores beyond the first; at most 4.
    """

    def __init__(self, max_pending: int = 16, compute_device=None, threads: int | None = None):
        cores = usable_cores()
        self.phased = (
            compute_device is not None
            and torch.device(compute_device).type == "cpu"
            and torch.get_num_threads() >= cores
        )
        if threads is None:
            threads = min(4, cores if self.phased else (cores - 1) // 2)
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, max_pending))
        self._error: BaseException | None = None
        self._lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._work, name=f"d2turb-writer-{i}", daemon=True) for i in range(max(1, threads))
        ]
        for t in self._threads:
            t.start()
        self._closed = False

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    fn, args, kwargs = job
                    fn(*args, **kwargs)
            except BaseException as exc:  # handed to the caller's thread
                with self._lock:
                    if self._error is None:
                        self._error = exc
            finally:
                self._queue.task_done()

    def _raise_error(self) -> None:
        if self._error is not None:  # sticky: the jobs after a failed one stay dropped
            raise self._error

    def submit(self, fn: Callable, *args, **kwargs) -> None:
        """Queue ``fn(*args, **kwargs)``; raises the error of an earlier job, if any."""
        if self._closed:
            raise RuntimeError("BackgroundWriter is closed")
        self._raise_error()
        self._queue.put((fn, args, kwargs))

    def before_compute(self) -> None:
        """When phased, block until the queued jobs are done (raising the error of one, if any)."""
        if self.phased:
            self._queue.join()
            self._raise_error()

    def close(self, cancel: bool = False) -> None:
        """Finish (or, with ``cancel``, drop) the queued jobs, stop the threads, raise a job's error."""
        if self._closed:
            return
        self._closed = True
        if cancel:
            while True:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    break
                self._queue.task_done()
        for _ in self._threads:
            self._queue.put(None)
        for t in self._threads:
            t.join()
        self._raise_error()

    def __enter__(self) -> BackgroundWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:  # the block's exception wins; a writer error would only hide it
            with contextlib.suppress(Exception):
                self.close(cancel=True)
