"""`d2turb app` as a user meets it: a server process on a free localhost port, driven through its HTTP API with
gradio_client (one simulate, one restore with a tiny model, one bad upload) and loaded by a real headless chromium
(skipped where no chromium/chromedriver/selenium is installed). The server runs with its own HOME, working folder
and TMPDIR, so the test also sees that it writes nothing outside its temp folder and removes that on exit."""

import importlib.util
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from d2turb.defaults import DEFAULT_OVERLAP_PX, DEFAULT_TILE_PX

if importlib.util.find_spec("gradio") is None:  # the server needs it; this process only needs the client
    pytest.skip("gradio is not installed (pip install 'd2turb[app]')", allow_module_level=True)
gradio_client = pytest.importorskip("gradio_client")

SRC = Path(__file__).resolve().parents[1] / "src"
START_TIMEOUT_S = 300  # importing torch + gradio on a loaded 2-core machine
CALL_TIMEOUT_S = 300


@pytest.fixture(autouse=True)
def _torch_threads():
    """Tiny tensors: one thread (a loaded machine makes a second thread wait for time slices)."""
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(2)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_d2turb_weights):
    root = tmp_path_factory.mktemp("app_server")
    home, cwd, tmp = (root / n for n in ("home", "cwd", "tmp"))
    for d in (home, cwd, tmp):
        d.mkdir()
    weights = tiny_d2turb_weights.parent
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GRADIO_", "D2TURB_", "MPLCONFIGDIR"))}
    env.update(
        HOME=str(home),
        TMPDIR=str(tmp),
        PYTHONPATH=str(SRC),
        D2TURB_WEIGHTS_DIR=str(weights),
        OMP_NUM_THREADS="1",
        PYTHONDONTWRITEBYTECODE="1",
    )
    port = _free_port()
    log = root / "server.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "d2turb", "app", "--port", str(port)],
            cwd=cwd,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    url = f"http://127.0.0.1:{port}/"
    deadline = time.monotonic() + START_TIMEOUT_S
    while f"d2turb app: {url}" not in log.read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"the app did not start (exit {proc.poll()}):\n{log.read_text()[-3000:]}")
        time.sleep(0.5)
    yield SimpleNamespace(url=url, port=port, home=home, cwd=cwd, tmp=tmp, weights=weights, log=log, proc=proc)
    proc.send_signal(signal.SIGTERM)
    try:
        assert proc.wait(timeout=120) == 0, log.read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert list(tmp.iterdir()) == [], "the app's temp folder is removed on exit"


def _listening_addresses(port: int) -> set[str]:
    """Local addresses (hex, as Linux writes them) of the sockets listening on ``port``."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(table):
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            address, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                found.add(address)
    return found


def test_binds_localhost_only(server):
    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("no /proc/net/tcp (not Linux)")
    assert _listening_addresses(server.port) == {"0100007F"}  # 127.0.0.1, nothing else


def _client(server, tmp_path):
    return gradio_client.Client(server.url, verbose=False, download_files=str(tmp_path / "dl"), analytics_enabled=False)


def _pixels(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)


def _rerun(command: str, bundle: str, tmp_path: Path, monkeypatch) -> Path:
    """Run the page's command line with the CLI (this process) in the unpacked download → its out/ folder."""
    from d2turb.cli import main

    with zipfile.ZipFile(bundle) as zf:
        zf.extractall(tmp_path / "again")
    (folder,) = list((tmp_path / "again").iterdir())
    shutil.rmtree(folder / "out")
    monkeypatch.chdir(folder)
    assert main(shlex.split(command)[1:]) == 0
    return folder / "out"


def test_http_api_simulate_restore_and_errors(server, tmp_path, monkeypatch):
    client = _client(server, tmp_path)
    job = client.submit(
        source="sample",
        sample="chart",
        upload=None,
        strength="D/r0",
        dr0=2.0,
        cn2=1e-14,
        aperture=0.1,
        wavelength="525",
        path_length=1000,
        ifov=0,
        depth="prior",
        depth_upload=None,
        disparity=False,
        modulation="power_offset",
        offset=0.5,
        seed=3,
        api_name="/simulate",
    )
    turb, tilt, flow_png, depth, modulation, table, derived, command, files = job.result(timeout=CALL_TIMEOUT_S)
    by_name = {Path(f).name: f for f in files}
    assert _pixels(turb).shape == _pixels(tilt).shape == (192, 256, 3)
    assert _pixels(flow_png).shape == (192, 256, 3)
    m = np.asarray(Image.open(modulation))  # 8-bit grey; Eq. 3 with s = 0.5: M in [0.5^0.6, 1] = [0.66, 1]
    assert m.shape == (192, 256) and m.min() >= np.floor(255 * 0.5**0.6) and m.max() == 255
    assert derived["dr0"] == 2.0 and derived["bin"] == "weak" and derived["r0_m"] == pytest.approx(0.05)
    assert "| strength bin | weak" in table
    flow = np.load(by_name["chart_fwd_flow_px.npy"])
    assert flow.shape == (2, 192, 256)
    assert derived["flow_scale_px"] == pytest.approx(float(np.linalg.norm(flow, axis=0).max()), rel=1e-5)
    # the chart's straight lines are bent: I_tilt differs from the clean chart, I_turb is also blurred
    assert np.abs(_pixels(turb) - _pixels(tilt)).mean() > 1
    np.testing.assert_array_equal(_pixels(turb), _pixels(by_name["chart_turb.png"]))
    assert command.startswith("d2turb simulate chart.png --out out --seed 3 --dr0 2.0 --depth prior")
    # the command line, run by the CLI in this process, writes the same pictures (up to one 8-bit level)
    again = _rerun(command, by_name["d2turb_simulate_chart.zip"], tmp_path / "sim", monkeypatch)
    for name in ("chart_turb.png", "chart_tilt.png"):
        assert np.abs(_pixels(again / name) - _pixels(by_name[name])).max() <= 1, name
    np.testing.assert_allclose(np.load(again / "chart_fwd_flow_px.npy"), flow, atol=1e-4)

    from d2turb.data.samples import sample_images
    from d2turb.io import write_image

    photo = tmp_path / "coffee.png"
    write_image(photo, sample_images()["coffee"])
    job = client.submit(
        upload=gradio_client.handle_file(str(photo)),
        weights="tiny-app",
        weights_path="",
        tile=128,
        overlap=32,
        device="cpu",
        api_name="/restore",
    )
    pair, flow_png, niqe_md, details, command, files = job.result(timeout=CALL_TIMEOUT_S)
    before, after = (_pixels(p) for p in pair)
    assert before.shape == after.shape == (192, 256, 3)
    np.testing.assert_array_equal(before, _pixels(photo))
    assert np.abs(after - before).mean() > 1  # a random model changes the picture
    assert all(isinstance(v, float) and v > 0 for v in details["niqe"].values())
    assert "| restored |" in niqe_md and details["flow_scale_px"] > 0.1
    assert command == "d2turb restore coffee.png --weights tiny-app --out out --tile 128 --overlap 32 --save-flow"
    by_name = {Path(f).name: f for f in files}
    monkeypatch.setenv("D2TURB_WEIGHTS_DIR", str(server.weights))
    again = _rerun(command, by_name["d2turb_restore_coffee.zip"], tmp_path / "res", monkeypatch)
    assert np.abs(_pixels(again / "coffee_restored.png") - after).max() <= 1

    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    with pytest.raises(gradio_client.exceptions.AppError) as info:
        client.predict(
            upload=gradio_client.handle_file(str(bad)),
            weights="input",
            weights_path="",
            tile=DEFAULT_TILE_PX,
            overlap=DEFAULT_OVERLAP_PX,
            device="cpu",
            api_name="/restore",
        )
    message = str(info.value)
    assert message.startswith("broken.png: cannot read image") and "Traceback" not in message, message

    # nothing was written outside the app's temp folder
    assert list(server.home.rglob("*")) == [] and list(server.cwd.rglob("*")) == []
    assert [p.name.startswith("d2turb-app-") for p in server.tmp.iterdir()] == [True]


def _browser():
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not (chromium and driver):
        pytest.skip("no chromium/chromedriver installed (Debian: apt-get install chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver")
    return webdriver, chromium, driver


def test_browser_renders_a_simulation(server, tmp_path, monkeypatch):
    webdriver, chromium, driver_path = _browser()
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    monkeypatch.setenv("SE_OFFLINE", "true")  # Selenium Manager must never download a driver or a browser
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        opts.add_argument(arg)
    opts.add_argument("--window-size=1280,1300")
    opts.add_argument(f"--user-data-dir={tmp_path / 'chromium'}")
    browser = webdriver.Chrome(service=Service(driver_path), options=opts)
    try:
        browser.get(server.url)
        WebDriverWait(browser, START_TIMEOUT_S).until(lambda b: b.find_elements(By.ID, "simulate-button"))
        browser.find_element(By.ID, "simulate-button").click()
        loaded = "const i = document.querySelector('#sim-turb img'); return i && i.complete ? i.naturalWidth : 0;"
        WebDriverWait(browser, CALL_TIMEOUT_S).until(lambda b: b.execute_script(loaded) > 0)
        assert browser.execute_script(loaded) == 256  # the astronaut sample, 256 px wide
        browser.execute_script("window.scrollTo(0, 0)")
        time.sleep(1.0)  # let the layout settle before the picture is taken
        shot = tmp_path / "page.png"
        browser.save_screenshot(str(shot))
        box = browser.execute_script(
            "const r = document.querySelector('#sim-turb img').getBoundingClientRect();"
            "return [r.left, r.top, r.width, r.height, window.devicePixelRatio];"
        )
        # the page fetched nothing from anywhere but the app (fonts, scripts, pictures), except the one script
        # tag Gradio's own page carries for pages embedded in an iframe (loaded async; offline it just fails)
        fetched = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
        outside = [u for u in fetched if not u.startswith((server.url, "data:", "blob:"))]
        assert fetched and all("/iframe-resizer/" in u for u in outside), outside
        # bad input: one clear line in the page, no stack trace
        bad = tmp_path / "broken.png"
        bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
        tabs = browser.find_elements(By.CSS_SELECTOR, "button[role=tab]")
        next(t for t in tabs if t.text.strip() == "Restore").click()
        WebDriverWait(browser, 60).until(lambda b: b.find_elements(By.CSS_SELECTOR, "#restore-upload input[type=file]"))
        browser.find_element(By.CSS_SELECTOR, "#restore-upload input[type=file]").send_keys(str(bad))
        browser.find_element(By.ID, "restore-button").click()
        message = "broken.png: cannot read image"
        WebDriverWait(browser, CALL_TIMEOUT_S).until(lambda b: message in b.find_element(By.TAG_NAME, "body").text)
        assert "Traceback" not in browser.find_element(By.TAG_NAME, "body").text
    finally:
        browser.quit()
    left, top, width, height, ratio = box
    page = np.asarray(Image.open(shot).convert("RGB"), dtype=np.float64)
    crop = page[int(top * ratio) : int((top + height) * ratio), int(left * ratio) : int((left + width) * ratio)]
    assert crop.shape[0] > 50 and crop.shape[1] > 50
    assert crop.std() > 20  # a photograph, not an empty placeholder
    target = os.environ.get("D2TURB_APP_SCREENSHOT")
    if target:  # regenerate the README's picture: D2TURB_APP_SCREENSHOT=docs/images/app.png pytest ...
        Image.open(shot).convert("RGB").quantize(colors=256).save(target, optimize=True)
