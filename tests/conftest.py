import hashlib
import os
import shutil
import sys
from pathlib import Path

# One BLAS thread in every process of the suite (this one, the CLI runs and the Dask workers
# it starts): OpenBLAS rounds differently with different thread counts (0.3.31: relative
# 1e-9 in the corrections of the test blocks), and the kill-and-resume and distributed tests
# compare runs in different processes bit for bit. (sapgo's own parallelism, independent
# subtrees on numba's threads, stays on.)
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

import sapgo  # noqa: E402
import sapgo.kernelcache  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

# The command line's notice on a fresh kernel cache ("compiling the numerical kernels ...,
# once") goes to the first command of a process: the one-line error tests would see it
# when they happen to run first after a change of the kernels.
sapgo.kernelcache.FIRST_RUN = False

threadpool_limits(1, user_api="blas")
from sapgo.project import Project, write_project  # noqa: E402


@pytest.fixture(scope="session")
def block_cache(tmp_path_factory):
    """Generated projects, made once per session; tests get copies."""
    root = tmp_path_factory.mktemp("blocks")
    made = {}

    def get(name, **params):
        key = (name, tuple(sorted(params.items())))
        if key not in made:
            path = root / f"{name}-{len(made)}.h5"
            sapgo.generate_block(path, **params)
            made[key] = path
        return made[key]

    return get


@pytest.fixture
def small_block(block_cache, tmp_path):
    """A copy of a 2-strip, 6-photo block (unordered, not adjusted)."""
    src = block_cache("small", strips=2, photos_per_strip=6, control_points=6)
    dst = tmp_path / "small.h5"
    shutil.copy(src, dst)
    return dst


@pytest.fixture
def p1_block(block_cache, tmp_path):
    """A copy of the SAPGO-P data set 1 block (unordered, not adjusted)."""
    dst = tmp_path / "p1.h5"
    shutil.copy(block_cache("p1", preset="sapgo-p-1"), dst)
    return dst


def read_records(path):
    with Project(path) as p:
        rec = {k: p.read(k) for k in ("cameras", "stations", "points", "observations",
                                      "station_priors")}
        rec["truth"] = ({"stations": p.read("truth/stations"), "points": p.read("truth/points")}
                        if p.has_truth else None)
    return rec


def rewrite(path, rec):
    """Write records (possibly changed) back as a new, unordered project."""
    obs = rec["observations"]
    counts = np.bincount(obs["point"], minlength=len(rec["points"]))
    starts = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    rec["points"]["obs_start"] = starts
    rec["points"]["n_obs"] = counts
    write_project(path, rec["cameras"], rec["stations"], rec["points"], obs,
                  rec["station_priors"], rec["truth"])


def collinear_control(path):
    """Leave 3 full control points, on one straight line: they pass the count check but
    leave the rotation about that line free (a datum defect only the pivot finds)."""
    rec = read_records(path)
    pt = rec["points"]
    ctrl = np.flatnonzero(pt["kind"] == 1)
    pt["kind"][ctrl[3:]] = 4
    line = pt["control"][ctrl[0]]
    for i, j in enumerate(ctrl[:3]):
        pt["control"][j] = line + i * np.array([1000.0, 10.0, 0.0])
        pt["xyz"][j] = pt["control"][j]
    rewrite(path, rec)


def digest(path):
    """SHA-256 of a file: a project left as it was has the same digest."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_cli(capsys, *args):
    """Run the command line in process; returns (exit code, stdout, stderr)."""
    from sapgo.cli import main

    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err, *words):
    """Exit code 2 and one line ``sapgo: error: ...`` holding every word, no traceback."""
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("sapgo: error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], lines[0]
