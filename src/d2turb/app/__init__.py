"""``d2turb app``: a local web page to turn the simulator's physical knobs and to restore images (optional extra
``pip install "d2turb[app]"``, Gradio). :mod:`d2turb.app.core` holds the work in plain Python (no gradio; modules
by concern: forms, jobs, tabs, views, workspace); :mod:`d2turb.app.ui` builds the page and serves it. See
docs/app.md."""
