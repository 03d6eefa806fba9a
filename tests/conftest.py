import os
from pathlib import Path

# Under pytest-xdist (the default run, `-n auto` in pyproject.toml) each worker gets one thread, and so do the
# processes tests start (OMP_NUM_THREADS, set before torch is imported); a serial run (`-n 0`) keeps two.
# D2TURB_TEST_THREADS overrides both.
TEST_THREADS = int(os.environ.get("D2TURB_TEST_THREADS", "1" if "PYTEST_XDIST_WORKER" in os.environ else "2"))
if "PYTEST_XDIST_WORKER" in os.environ:
    os.environ["OMP_NUM_THREADS"] = str(TEST_THREADS)

import pytest  # noqa: E402
import torch  # noqa: E402

SHARED_DATA = Path(
    os.environ.get("D2TURB_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
).resolve()


def pytest_xdist_auto_num_workers(config):
    """`-n auto`: xdist's one worker per core for the suite, but a run of a single test file stays in this
    process (starting workers that each import torch costs more than they save there)."""
    files = {str(arg).split("::")[0] for arg in config.args}
    if len(files) == 1 and next(iter(files)).endswith(".py"):
        return 0
    return None


# Tests marked `@pytest.mark.slow` take over ~2 s of CPU (measured: per-test getrusage deltas of the whole suite,
# children included). They still run everywhere (nothing deselects them unless you pass `-m "not slow"`); under xdist
# they come first in the list the workers split and steal from (`--dist worksteal`, pyproject.toml), so that no worker
# starts a 10 s test at the end.
def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: slow first


@pytest.fixture(autouse=True)
def _torch_threads():
    torch.set_num_threads(TEST_THREADS)


@pytest.fixture(autouse=True)
def _deprecations_warn_again():
    """Deprecated names warn once per process (d2turb.deprecation); every test starts with none warned."""
    from d2turb.deprecation import reset

    reset()


@pytest.fixture
def shared_data() -> Path:
    """../shared/data (real images); tests that need it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture
def astronaut() -> torch.Tensor:
    """A built-in natural RGB sample image (1, 3, 256, 256) in [0, 1]."""
    from skimage import data, transform

    img = transform.resize(data.astronaut(), (256, 256), anti_aliasing=True)
    return torch.from_numpy(img).float().permute(2, 0, 1)[None].contiguous()


class PublishedTiltCorrelation:
    """Independent oracle for tilt correlation (physics.md §2), straight from the published integral
    I_n(s) = ∫ z^(−14/3) J_n(2sz) J_2(z)² dz by adaptive quadrature (scipy ``quad``; the large-s tail by
    the integral's leading term (2s)^(−1/3)/64·∫x^(−2/3)J_n(x)dx), and the constant-Cn² path as the
    (1 − z/L)^(5/3)-weighted average over z by ``quad_vec``. Shares no code with d2turb.sim.tilt."""

    S_QUAD = 50.0

    def __init__(self):
        import numpy as np
        from scipy import integrate, special

        def integral(n, s):
            # z = u³ removes the z^(−2/3) cusp at 0; the integrand is negligible beyond z = 80
            f = lambda u: 3 * u**-12 * special.jv(n, 2 * s * u**3) * special.jv(2, u**3) ** 2  # noqa: E731
            return integrate.quad(f, 1e-9, 80 ** (1 / 3), limit=800, epsabs=1e-10, epsrel=1e-8)[0]

        self.s = np.concatenate([[0.0], np.geomspace(1e-4, self.S_QUAD, 160)])
        self.i0 = np.array([integral(0, s) for s in self.s])
        self.i2 = np.array([integral(2, s) for s in self.s])
        self.norm = self.i0[0]
        mellin = {n: 2 ** (-2 / 3) * special.gamma((n + 1 / 3) / 2) / special.gamma((n + 5 / 3) / 2) for n in (0, 2)}
        self.tail = {n: (lambda s, m=mellin[n]: (2 * s) ** (-1 / 3) / 64 * m) for n in (0, 2)}
        self._np, self._integrate = np, integrate

    def layer(self, s):
        """(perpendicular, parallel) correlation of one layer at normalised separation s."""
        np = self._np
        s = np.abs(np.asarray(s, dtype=np.float64))
        logs = np.log(np.maximum(s, 1e-4))
        grid = np.log(np.maximum(self.s, 1e-4))
        i0 = np.where(s <= self.S_QUAD, np.interp(logs, grid, self.i0), self.tail[0](np.maximum(s, 1e-9)))
        i2 = np.where(s <= self.S_QUAD, np.interp(logs, grid, self.i2), self.tail[2](np.maximum(s, 1e-9)))
        i2 = np.where(s < 1e-4, 0.0, i2)
        return (i0 + i2) / self.norm, (i0 - i2) / self.norm

    def path(self, s_of_t):
        """(perpendicular, parallel) averaged over the path: ∫ c(s(t)) (1 − t)^(5/3) dt / ∫ (1 − t)^(5/3) dt,
        t = z/L, with ``s_of_t(t)`` the array of separations seen by the layer at t."""
        np = self._np

        def f(t):
            perp, par = self.layer(s_of_t(t))
            return np.concatenate([perp, par]) * (1 - t) ** (5 / 3)

        val = self._integrate.quad_vec(f, 0.0, 1.0, epsabs=1e-6, epsrel=1e-6, limit=400)[0] / (3 / 8)
        half = len(val) // 2
        return val[:half], val[half:]


@pytest.fixture(scope="session")
def published_tilt():
    return PublishedTiltCorrelation()


@pytest.fixture(scope="session")
def tiny_d2turb_weights(tmp_path_factory) -> Path:
    """A tiny random D²Turb (NAFNet + U-Net rectifier) with a non-zero flow head, saved as safetensors in a
    folder of its own (usable as $D2TURB_WEIGHTS_DIR)."""
    from _tiny_models import tiny_d2turb

    from d2turb.models import save_pretrained

    model = tiny_d2turb(flow_std=2.0)
    return save_pretrained(model.eval(), tmp_path_factory.mktemp("weights") / "tiny-app.safetensors")


@pytest.fixture
def run_unprivileged():
    """Run ``python -m d2turb ARGS`` in a process that file permissions bind: as root (CI), under ``setpriv`` with
    CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH dropped from the bounding set, so that mode 000 and read-only
    folders refuse it as they refuse a normal user; as another user, directly. Returns the CompletedProcess."""
    import shutil
    import subprocess
    import sys

    if os.name != "posix":
        pytest.skip("needs POSIX permissions")
    prefix = []
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            pytest.skip("running as root without setpriv (util-linux) to drop the permission override")
        prefix = [setpriv, "--bounding-set=-dac_override,-dac_read_search"]
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}

    def run(*args, timeout: float = 300):
        cmd = [*prefix, sys.executable, "-m", "d2turb", *map(str, args)]
        return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)

    return run
