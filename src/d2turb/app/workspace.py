"""The app's files: one temp folder for everything (:class:`Workspace`), gradio's environment pointed into it, and
the zip bundle of a run that the page offers as a download."""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import uuid
import zipfile
from pathlib import Path


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
    os.environ["GRADIO_TEMP_DIR"] = str(workspace.root / "gradio")
    os.environ["GRADIO_ANALYTICS_ENABLED"] = "False"
    os.environ.setdefault("MPLCONFIGDIR", str(workspace.root / "matplotlib"))


def bundle(run: Path, name: str) -> Path:
    """Zip everything of a run (inputs, out/, views/, command.sh) into run/name.zip."""
    target = run / f"{name}.zip"
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_STORED) as zf:
        for p in sorted(run.rglob("*")):
            if p.is_file() and p != target:
                zf.write(p, Path(name) / p.relative_to(run))
    return target
