"""The band's factor replayed instead of stored (``--factor-storage replay``): the same
adjustment as with the factor file, its scratch a solver state per segment."""

import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

import sapgo
import sapgo.solve.band as band_mod
from conftest import read_records, rewrite
from sapgo.project import Project
from sapgo.work import work_path

OPTS = dict(progress=False, chunk_points=40, chunk_rows=2)


@pytest.fixture(scope="module")
def prior_block(block_cache, tmp_path_factory):
    """A 4 x 30 block with GNSS priors on every fifth photo and 6 planted blunders,
    ordered (band)."""
    d = tmp_path_factory.mktemp("replay")
    path = d / "block.h5"
    rec = read_records(block_cache("replay", strips=4, photos_per_strip=30, control_points=10,
                                   blunders=6, seed=3))
    st = rec["stations"]
    some = np.arange(0, len(st), 5)
    pr = np.zeros(len(some), rec["station_priors"].dtype)
    pr["station"] = some
    pr["value"] = st["eo"][some]
    pr["weight"] = np.diag([0, 0, 0, 0.04, 0.04, 0.04])
    rec["station_priors"] = pr
    rewrite(path, rec)
    sapgo.order_project(path, solver="band")
    return path


def run(src, tmp_path, name, **kw):
    path = tmp_path / f"{name}.h5"
    shutil.copy(src, path)
    s = sapgo.adjust(path, sapgo.Options(**OPTS, **kw))
    with Project(path) as p:
        out = {k: p.solution(k) for k in ("station_sigma", "point_sigma", "residuals",
                                          "obs_quality")}
        out["eo"] = p.read("stations")["eo"]
        out["xyz"] = p.read("points")["xyz"]
        out["report"] = json.loads(p.file["solution/report"][()])
    return s, out


def fields(a):
    return a.dtype.names or [None]


def equal(x, y, rtol, what):
    for n in fields(x):
        u, v = (x, y) if n is None else (x[n], y[n])
        if np.issubdtype(u.dtype, np.floating):
            scale = np.nanmax(np.abs(u)) if u.size else 1.0
            np.testing.assert_allclose(v, u, rtol=0, atol=rtol * scale, err_msg=f"{what} {n}")
        else:
            np.testing.assert_array_equal(v, u, err_msg=f"{what} {n}")


@pytest.mark.parametrize("method", ["gauss-newton", "levenberg-marquardt"])
def test_replay_gives_the_file_s_adjustment(prior_block, tmp_path, monkeypatch, method):
    """Many segments (a factored chunk each): the solution and the precision equal the
    file's (with Gauss-Newton the precision pass reads the last step's factor: the replay
    builds its rows from the state before that step)."""
    monkeypatch.setattr(band_mod, "REPLAY_SEGMENT_BYTES", 1)
    made = []
    real = band_mod.FactorReplay._replay

    def counting(self, j):
        made.append(self.J)
        return real(self, j)

    monkeypatch.setattr(band_mod.FactorReplay, "_replay", counting)
    s_f, f = run(prior_block, tmp_path, "file", factor_storage="file", method=method)
    assert not made
    s_r, r = run(prior_block, tmp_path, "replay", factor_storage="replay", method=method)
    assert made and min(made) > 10   # many segments, replayed
    assert s_r.iterations == s_f.iterations and s_r.sigma0 == pytest.approx(s_f.sigma0,
                                                                             rel=1e-12)
    for k in ("eo", "xyz", "residuals"):
        equal(f[k], r[k], 1e-12, k)
    for k in ("station_sigma", "point_sigma", "obs_quality"):
        equal(f[k], r[k], 1e-12, k)


@pytest.mark.parametrize("kw", [dict(method="gauss-newton"), dict(snooping=True),
                                dict(calibrate=("f",)), dict(datum="free")])
def test_factor_in_core_is_the_file_s_bit_for_bit(prior_block, tmp_path, kw):
    """The factor rows in core (the same kernels, taken out of the solver's ring straight
    into the arrays): every result equal to the file's to the last bit, with snooping,
    self-calibration's border and a free network's inner precision too; nothing written."""
    s_f, f = run(prior_block, tmp_path, "file", factor_storage="file", **kw)
    path = tmp_path / "kept.h5"
    shutil.copy(prior_block, path)
    s_c = sapgo.adjust(path, sapgo.Options(**OPTS, factor_storage="core", keep_scratch=True,
                                           **kw))
    names = {x.name for x in work_path(path).iterdir()}
    assert not {"factor.bin", "y.bin", "replay.bin"} & names
    _, c = run(prior_block, tmp_path, "core", factor_storage="core", **kw)
    assert s_c.iterations == s_f.iterations and s_c.sigma0 == s_f.sigma0
    for k in ("eo", "xyz", "residuals", "station_sigma", "point_sigma", "obs_quality"):
        equal(f[k], c[k], 0, k)


def test_replay_with_snooping_rejects_the_same(prior_block, tmp_path, monkeypatch):
    monkeypatch.setattr(band_mod, "REPLAY_SEGMENT_BYTES", 1)
    s_f, f = run(prior_block, tmp_path, "file", factor_storage="file", snooping=True)
    s_r, r = run(prior_block, tmp_path, "replay", factor_storage="replay", snooping=True)
    assert s_f.rejected
    assert [x["observation"] for x in s_r.rejected] == [x["observation"] for x in s_f.rejected]
    np.testing.assert_allclose([x["w"] for x in s_r.rejected], [x["w"] for x in s_f.rejected],
                               rtol=1e-12)
    equal(f["eo"], r["eo"], 1e-12, "eo")
    equal(f["obs_quality"], r["obs_quality"], 1e-12, "quality")


def test_replay_free_network_and_scratch(block_cache, tmp_path, monkeypatch):
    """A free network (inner constraints: its precision solves through the factor forward
    and back) equals the file's; the work directory holds no factor file."""
    monkeypatch.setattr(band_mod, "REPLAY_SEGMENT_BYTES", 1)
    src = tmp_path / "free.h5"
    shutil.copy(block_cache("replay-free", strips=3, photos_per_strip=12, control_points=6),
                src)
    sapgo.order_project(src, solver="band")
    _, f = run(src, tmp_path, "file", factor_storage="file", datum="free")
    path = tmp_path / "kept.h5"
    shutil.copy(src, path)
    sapgo.adjust(path, sapgo.Options(**OPTS, factor_storage="replay", datum="free",
                                     keep_scratch=True))
    names = {x.name for x in work_path(path).iterdir()}
    assert "replay.bin" in names and "factor.bin" not in names
    _, r = run(src, tmp_path, "replay", factor_storage="replay", datum="free")
    for k in ("eo", "xyz", "station_sigma", "point_sigma"):
        equal(f[k], r[k], 1e-10, k)


def test_replay_refused_with_self_calibration_and_auto_keeps_the_file(prior_block, tmp_path,
                                                                       capsys):
    from sapgo.cli import main

    path = tmp_path / "cal.h5"
    shutil.copy(prior_block, path)
    code = main(["adjust", str(path), "--no-progress", "--calibrate", "f",
                 "--factor-storage", "replay"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "self-calibration's border needs the factor file" \
        in err[0]
    s = sapgo.adjust(path, sapgo.Options(**OPTS, calibrate=("f",)))
    assert s.converged


RUN = ("import sys, sapgo, sapgo.solve.band as b; b.REPLAY_SEGMENT_BYTES = 1; "
       "sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, chunk_points=40, "
       "chunk_rows=2, factor_storage=sys.argv[2] if len(sys.argv) > 2 else 'replay', "
       "resume=len(sys.argv) > 2))")


@pytest.mark.parametrize("fault, resume_with", [("solve:2", "replay"), ("build:2", "replay"),
                                                ("update:1", "replay"), ("solve:2", "file"),
                                                ("update:2", "core")])
def test_replay_killed_and_resumed(prior_block, tmp_path, monkeypatch, fault, resume_with):
    """Killed anywhere, resumed: the uninterrupted result, also when the resumed run keeps
    its factor in a file or in core (``auto`` may choose otherwise once the free disk has
    changed)."""
    monkeypatch.setattr(band_mod, "REPLAY_SEGMENT_BYTES", 1)
    _, ref = run(prior_block, tmp_path, "ref", factor_storage="replay")
    path = tmp_path / "killed.h5"
    shutil.copy(prior_block, path)
    r = subprocess.run([sys.executable, "-c", RUN, str(path)], capture_output=True, text=True,
                       env=dict(os.environ, SAPGO_FAULT=fault), timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    r = subprocess.run([sys.executable, "-c", RUN, str(path), resume_with],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "cannot be resumed" not in r.stderr
    with Project(path) as p:
        eo = p.read("stations")["eo"]
        sig = p.solution("station_sigma")
    equal(ref["eo"], eo, 0 if resume_with == "replay" else 1e-12, "eo")
    equal(ref["station_sigma"], sig, 0 if resume_with == "replay" else 1e-12, "station_sigma")


def test_auto_replays_beyond_its_share_of_memory(prior_block, tmp_path, monkeypatch):
    """``--factor-storage auto``: in core up to a quarter of the memory budget, the file up
    to half the machine's memory in factor rows, the replay beyond (shares made tiny here);
    the same adjustment in each."""
    import importlib

    adjust_mod = importlib.import_module("sapgo.adjust")
    assert adjust_mod.factor_file_limit() > 1 << 28
    assert adjust_mod.factor_core_limit(sapgo.Options()) == 1 << 28
    assert adjust_mod.factor_core_limit(sapgo.Options(memory="2G")) == 1 << 29
    eo = {}
    for core, fraction, expect in [(1 / 4, 1 / 2, None), (1e-12, 1 / 2, "factor.bin"),
                                   (1e-12, 1e-12, "replay.bin")]:
        monkeypatch.setattr(adjust_mod, "FACTOR_CORE_FRACTION", core)
        monkeypatch.setattr(adjust_mod, "FACTOR_FILE_FRACTION", fraction)
        path = tmp_path / f"auto-{expect}.h5"
        shutil.copy(prior_block, path)
        sapgo.adjust(path, sapgo.Options(**OPTS, keep_scratch=True))
        names = {x.name for x in work_path(path).iterdir()}
        assert ({"factor.bin", "replay.bin"} - {expect}).isdisjoint(names)
        assert expect is None or expect in names
        with Project(path) as p:
            eo[expect] = p.read("stations")["eo"]
    equal(eo["factor.bin"], eo[None], 1e-12, "eo in core")
    equal(eo["factor.bin"], eo["replay.bin"], 1e-12, "eo replayed")
