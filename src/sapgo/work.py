"""The work directory of a run: its scratch record files, its checkpoint, and the fault
injection that the crash-safety tests kill a run with (DESIGN section 2, "Crash safety").

Band rows, right-hand side, point coordinates and residuals live in direct-access files
(:class:`sapgo.rawfile.RawArray`) in ``NAME.h5.work/`` beside the project; point coordinates
and residuals are double-buffered and the checkpoint is replaced atomically once an
iteration is complete, so that a run killed at any moment resumes from its last completed
iteration (``sapgo adjust --resume``).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np

from . import paging
from .project import Project
from .rawfile import CoreArray, RawArray


def work_path(path):
    """The work directory of a run on ``path``: ``NAME.h5.work`` beside the project."""
    path = Path(path)
    return path.with_name(path.name + ".work")


#: Fault injection for the crash-safety tests: ``SAPGO_FAULT=phase:iteration`` kills the
#: process with SIGKILL when it reaches that point (phases: build, solve, update,
#: checkpoint, commit-copy, commit-write, commit-replace; iteration ``*`` for any).
FAULT_ENV = "SAPGO_FAULT"


def _fault(phase, iteration=0):
    """``SAPGO_FAULT=phase:iteration`` kills the process there; ``enospc@phase:iteration``
    raises the error of a full disk there instead (the disk-full tests)."""
    spec = os.environ.get(FAULT_ENV)
    if not spec:
        return
    kind, _, spec = spec.rpartition("@")
    want_phase, _, want_it = spec.partition(":")
    if want_phase == phase and want_it in ("*", "", str(iteration)):
        if kind == "enospc":
            import errno

            raise OSError(errno.ENOSPC, "No space left on device")
        os.kill(os.getpid(), signal.SIGKILL)


class Work:
    """The work directory of a run: scratch record files and the checkpoint.

    Files: ``factor.bin`` (n x 6 x 6b factor rows, diagonal-first), ``y.bin`` (n x 6, the
    forward-substituted right-hand side; both arrays in core instead with ``core``, and
    neither with ``replay``),
    ``xyz.0.bin`` / ``xyz.1.bin`` (point coordinates, double-buffered), ``residuals.0.bin`` /
    ``residuals.1.bin`` (vx, vy of every observation), ``eo.K.npy`` (the stations'
    orientation after iteration K) and ``checkpoint.json`` (the last completed iteration K,
    its log, timings and the identity of the project). State K uses buffer ``K % 2``.

    With ``files`` False (a run without work files, ``Options.work_files``) every one of
    these but the factor is an array in memory (:class:`sapgo.rawfile.CoreArray`; the
    factor with ``core``, as with files) and :meth:`save` writes no checkpoint: an
    interrupted run starts again. The directory is then made only for a factor beyond the
    memory budget (its file, or the replay's) or the partition tree's factor file.
    """

    def __init__(self, path, p: Project, band_width, create, block=6, n_border=0,
                 replay=False, core=False, files=True):
        self._dir = Path(path)
        self.files = files
        self._core = {}   # (files False) the scratch arrays by name
        self.n_st, self.n_pt, self.n_obs = p.n_stations, p.n_points, p.n_observations
        self.band_width = band_width
        mode = "w" if create else "r+"
        if create and files:
            if self._dir.exists():
                shutil.rmtree(self._dir)
            self._dir.mkdir(parents=True)
        bw = band_width
        k = self.block = block
        core = core or (not files and bw == 0)   # (the tree's run: no band rows to keep)
        if create:   # (the files are sparse: the bytes they can come to)
            from .project import ensure_free

            rows = 0 if core else k * (k * bw + 1)
            if replay:   # a solver state (k b columns of k b + P doubles) a segment
                from .solve.band import REPLAY_SEGMENT_BYTES

                seg = max(1, REPLAY_SEGMENT_BYTES // (8 * k * k * bw))
                rows = (k * bw) * (k * bw + 64) / seg
            rest = self.n_st * k * n_border + 2 * self.n_pt * 3 + 2 * self.n_obs * 2
            need = 8 * (self.n_st * rows + (rest if files else 0))
            if need:   # (without work files: only a factor beyond the budget is written)
                ensure_free(self.dir, need, "the run's work files")
        # (a replayed factor, sapgo.solve.band.FactorReplay, has no factor file: replay.bin)
        self.factor = self.y = None
        if core:   # in core (``--factor-storage core``): arrays, gone with the process
            self.factor = np.empty((self.n_st, k, k * bw))
            self.y = np.empty((self.n_st, k))
        elif not replay:   # (a run resumed with the file that started replaying makes it:
            # a resumed run factors anew before it reads the factor)
            fmode = mode if (self.dir / "factor.bin").exists() else "w"
            self.factor = RawArray(self.dir / "factor.bin", (self.n_st, k, k * bw), mode=fmode)
            self.y = RawArray(self.dir / "y.bin", (self.n_st, k), mode=fmode)
        #: the band factor's :class:`~sapgo.solve.band.FactorReplay` of the last
        #: factorisation (valid until the state changes), or None
        self.replay = None
        # self-calibration: the border columns of the band rows, then W = U'^-1 B
        self.border = (self.array("border.bin", (self.n_st, k, n_border), mode)
                       if n_border else None)
        self.xyz = [self.array(f"xyz.{i}.bin", (self.n_pt, 3), mode) for i in (0, 1)]
        self.res = [self.array(f"residuals.{i}.bin", (self.n_obs, 2), mode) for i in (0, 1)]
        self.state = 0  # the completed iteration whose buffers are current
        #: the partition tree's factor of the last factorisation
        #: (:class:`sapgo.solve.fronts.FactorFile`, in core or in ``tree_factor.bin``)
        self.tree_factor = None
        #: the in-core factor's buffer, kept from one step to the next
        self.tree_arena = None
        # robust estimation: the observations' redundancy (r_x, r_y, r_xy) of the
        # least-squares solution, once that phase is over
        self.robust_r = None
        if files and not create and (self._dir / "robust_r.bin").exists():
            self.robust_r = RawArray(self._dir / "robust_r.bin", (self.n_obs, 3), mode="r")

    @property
    def dir(self):
        """The work directory (made on first use by a run without work files)."""
        if not self.files and not self._dir.is_dir():
            self._dir.mkdir(parents=True)
        return self._dir

    def array(self, name, shape, mode="w", dtype="<f8"):
        """The scratch array ``name`` of ``shape``: the file ``name`` in the work directory
        (:class:`~sapgo.rawfile.RawArray`, opened with ``mode``), or without work files an
        array in memory kept by name (``mode`` "w" makes it anew, zeroed; "r" and "r+" find
        the one made before)."""
        if self.files:
            return RawArray(self.dir / name, shape, dtype, mode)
        a = self._core.get(name)
        if mode == "w" or a is None:
            if mode != "w":
                raise FileNotFoundError(f"no scratch array {name} in this run")
            a = self._core[name] = CoreArray(shape, dtype)
        return a

    def band_factor(self):
        """``(factor rows, y)`` of the last band factorisation: the files, or the replay's
        rows."""
        if self.replay is not None:
            return self.replay.factor, self.replay.y
        if self.factor is None:
            raise RuntimeError("the band factor was replayed and is stale: factor again")
        return self.factor, self.y

    def drop_replay(self):
        if self.replay is not None:
            self.replay.close()
            self.replay = None

    @property
    def xyz_current(self):
        return self.xyz[self.state % 2]

    @property
    def xyz_next(self):
        return self.xyz[(self.state + 1) % 2]

    @property
    def res_current(self):
        return self.res[self.state % 2]

    @property
    def res_next(self):
        return self.res[(self.state + 1) % 2]

    def initialise(self, p: Project, chunk):
        for a, b in p.chunks("points", chunk):
            self.xyz[0][a:b] = p.read_field("points", "xyz", a, b)

    def save(self, iteration, eo, record, cams=None):
        """Make iteration ``iteration`` the checkpoint (its buffers must be complete);
        ``cams``: the camera rows when the photos' intrinsics are adjusted. Without work
        files iteration ``iteration`` becomes the current state, and nothing is written."""
        if not self.files:
            _fault("checkpoint", iteration)
            self.state = iteration
            return
        eo_file = self.dir / f"eo.{iteration}.npy"
        tmp = self.dir / f"eo.{iteration}.npy.tmp"
        with open(tmp, "wb") as f:
            paging.save_npy(f, np.ascontiguousarray(eo))
        os.replace(tmp, eo_file)
        record = dict(record, iteration=iteration, eo_file=eo_file.name)
        if cams is not None:
            cams_file = self.dir / f"cams.{iteration}.npy"
            with open(self.dir / f"cams.{iteration}.npy.tmp", "wb") as f:
                np.save(f, cams)
            os.replace(self.dir / f"cams.{iteration}.npy.tmp", cams_file)
            record["cams_file"] = cams_file.name
        _fault("checkpoint", iteration)
        tmp = self.dir / "checkpoint.json.tmp"
        tmp.write_text(json.dumps(record))
        os.replace(tmp, self.dir / "checkpoint.json")
        self.state = iteration
        keep = {eo_file.name, record.get("cams_file")}
        for old in [*self.dir.glob("eo.*.npy"), *self.dir.glob("cams.*.npy")]:
            if old.name not in keep:
                old.unlink(missing_ok=True)

    @staticmethod
    def load_checkpoint(path):
        """The checkpoint record of an interrupted run in ``path``, or None."""
        f = Path(path) / "checkpoint.json"
        try:
            record = json.loads(f.read_text())
            eo_path = Path(path) / record["eo_file"]
            paging.npy_header(eo_path)   # (read by the run: paging.load_npy)
            if record.get("cams_file"):
                record["cams"] = np.load(Path(path) / record["cams_file"])
        except (OSError, ValueError, KeyError, SyntaxError):
            return None
        record["eo_path"] = eo_path
        return record

    def start_robust(self, quality, chunk):
        """Keep the least-squares redundancy numbers for the robust phase."""
        if not self.files:
            self.robust_r = self.array("robust_r.bin", (self.n_obs, 3))
            for a in range(0, self.n_obs, chunk):
                self.robust_r[a:a + chunk] = quality[a:a + chunk][:, :3]
            return
        tmp = self.dir / "robust_r.bin.tmp"
        r = RawArray(tmp, (self.n_obs, 3), mode="w")
        for a in range(0, self.n_obs, chunk):
            r[a:a + chunk] = quality[a:a + chunk][:, :3]
        r.close()
        os.replace(tmp, self.dir / "robust_r.bin")  # whole or absent after a kill
        self.robust_r = RawArray(self.dir / "robust_r.bin", (self.n_obs, 3), mode="r")

    def close(self):
        self.drop_replay()
        for a in [self.factor, self.y, *self.xyz, *self.res]:
            if isinstance(a, RawArray):
                a.close()
        if self.border is not None:
            self.border.close()
        if self.robust_r is not None:
            self.robust_r.close()
        if self.tree_factor is not None:
            self.tree_factor.close()
            self.tree_factor = None
        self.tree_arena = None


def _identity(p: Project, band_width):
    return {"project_uuid": p.attr("uuid", ""), "stations": p.n_stations,
            "points": p.n_points, "observations": p.n_observations, "band_width": band_width}
