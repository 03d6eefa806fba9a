"""Atomic writes: every output file is written under a temporary name next to it and renamed into place (mode 0666
minus the umask, as a normal write), so an interrupted run never leaves a half-written file; the temporary files of
a killed run are removed by the next one (:func:`remove_stale_temp_files`, :func:`check_output_dir`). Also the
exclusive lock of a folder by one run (:class:`FolderLock`)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import stat
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from d2turb.errors import D2TurbError

_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<token>[A-Za-z0-9_-]+)\.tmp(?P<suffix>\.[^.]+)?$")


def reason(exc: OSError) -> str:
    """What went wrong, in the words of the OS (``Permission denied``), for a one-line error."""
    return exc.strerror or str(exc) or exc.__class__.__name__


NAME_MAX = 255  # bytes in one file name (Linux, macOS, Windows)


def temp_name(name: str, token: str) -> str:
    """``.NAME.<token>.tmpSUFFIX``, with NAME's stem cut (at a character boundary, its suffix kept) so that the
    temp name fits in :data:`NAME_MAX` bytes whenever ``name`` does; :func:`remove_stale_temp_files` reads both."""
    suffix = Path(name).suffix
    tail = f".{token}.tmp{suffix}"
    if len(os.fsencode(f".{name}{tail}")) > NAME_MAX:  # fsencode: a name that is not UTF-8 counts its raw bytes
        stem = name[: len(name) - len(suffix)]
        room = NAME_MAX - len(os.fsencode(f".{suffix}{tail}"))
        cut = os.fsencode(stem)[: max(room, 1)]
        try:  # a UTF-8 name is cut at a character boundary; one that is not UTF-8 keeps its raw bytes
            stem.encode()
            name = cut.decode(errors="ignore") + suffix
        except UnicodeEncodeError:
            name = os.fsdecode(cut) + suffix
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
        raise D2TurbError(f"cannot write {path}: {reason(exc)}") from exc
    try:
        yield tmp
        if stat.S_IMODE(tmp.stat().st_mode) != mode:  # a writer that replaced the file (safetensors: 0600)
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except OSError as exc:
        raise D2TurbError(f"cannot write {path}: {reason(exc)}") from exc
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
        raise D2TurbError(f"cannot write {path}: {reason(exc)}") from exc
    try:
        with open(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise D2TurbError(f"cannot write {path}: {reason(exc)}") from exc
        raise


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def write_json(path: str | os.PathLike, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode())


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
            raise D2TurbError(f"cannot lock {self.folder}: {reason(exc)}") from exc
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
