"""`d2turb app`: the local web page (optional extra: pip install "d2turb[app]")."""

from __future__ import annotations

from d2turb.errors import D2TurbError

INSTALL_HINT = "d2turb app needs the app extra: pip install 'd2turb[app]' (from a checkout: pip install -e '.[app]')"


def register(sub):
    p = sub.add_parser(
        "app",
        help="local web page: simulate turbulence with physical knobs, restore images (needs d2turb[app])",
        description="Serve the d2turb page (Gradio) on HOST:PORT until Ctrl+C. Uploads and results live in one "
        "temp folder, removed on exit.",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=None, help="port (default: 7860 or the next free one)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.set_defaults(func=run)


def run(args) -> int:
    import importlib.util
    import signal
    import threading

    spec = importlib.util.find_spec("gradio")
    if spec is None or spec.origin in (None, "namespace"):  # no origin: a stray folder named gradio, not the package
        raise D2TurbError(INSTALL_HINT)
    # lazy: see d2turb.commands
    from d2turb.app.core import Workspace, prepare_environment

    workspace = Workspace()
    prepare_environment(workspace)  # before gradio is imported
    stop = threading.Event()
    demo = None
    try:
        try:
            # lazy: gradio is optional and reads GRADIO_TEMP_DIR on import (set just above)
            from d2turb.app.ui import serve
        except ImportError as exc:
            raise D2TurbError(f"cannot import gradio ({exc}); {INSTALL_HINT}") from exc
        demo, url = serve(args.host, args.port, workspace)
        print(f"d2turb app: {url} (Ctrl+C to stop)", flush=True)
        if args.open:
            import webbrowser

            webbrowser.open(url)
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        while not stop.wait(1.0):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        if demo is not None:
            demo.close()
        workspace.cleanup()
    return 0
