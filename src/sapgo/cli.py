"""The ``sapgo`` command line: argument parsing only; each command calls one function."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from . import __version__
from .errors import ParameterError, SapgoError


def _say(text=""):
    """Print a line of a command's output on standard output, at once. When the reader
    has gone (``sapgo info P | head -3``), the rest of the output is dropped without a
    word and the command goes on (the files it writes are still written; its exit code
    is its own)."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        _silence("stdout")


def _warn(msg):
    try:
        print(f"sapgo: warning: {msg}", file=sys.stderr, flush=True)
    except BrokenPipeError:
        _silence("stderr")


def _silence(name):
    """Send what is still to come on ``sys.stdout`` or ``sys.stderr`` (``name``) to
    the null device: its reader closed the pipe (Python's recipe for SIGPIPE, so that
    neither a later write nor the flush at exit complains about the broken pipe)."""
    stream = getattr(sys, name)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, stream.fileno())
    except (AttributeError, OSError, ValueError):  # (not a file: a test's stand-in)
        setattr(sys, name, open(os.devnull, "w"))
    finally:
        os.close(null)


def _ids(ids, limit=20):
    s = ", ".join(str(i) for i in ids[:limit])
    return s + (", ..." if len(ids) > limit else "")


def _report_exclusions(points, stations, n_points=None, n_stations=None):
    n_points = len(points) if n_points is None else n_points
    n_stations = len(stations) if n_stations is None else n_stations
    if n_points:
        _warn(f"{n_points} point(s) seen on fewer than 2 photos cannot be determined and "
              f"are left out of the adjustment (they stay in the project): ids {_ids(points)}")
    if n_stations:
        _warn(f"{n_stations} photo(s) with fewer than 3 determinable points are left out of "
              f"the adjustment (they stay in the project): ids {_ids(stations)}")


def _five_numbers(text):
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 5:
        raise argparse.ArgumentTypeError(f"expected 5 numbers separated by commas "
                                          f"(k1,k2,k3,p1,p2), got {text!r}")
    return values


def cmd_generate(args):
    from .generate import generate_block

    angle = args.station_angle_perturbation
    irregular = {}
    if any(v is not None for v in (args.shift, args.strip_lengths, args.strip_starts,
                                   args.scales)):
        irregular = dict(shift=args.shift, **_design_lists(args))
    info = generate_block(
        args.output, preset=args.preset, strips=args.strips,
        photos_per_strip=args.photos_per_strip, pattern=args.pattern,
        points_per_photo=args.points_per_photo, control_points=args.control_points, forelap=args.forelap, sidelap=args.sidelap,
        sigma_image=None if args.sigma_image is None else args.sigma_image / 1000.0,
        station_position_perturbation=args.station_position_perturbation,
        station_angle_perturbation=angle, control_perturbation=args.control_perturbation,
        terrain_relief=args.terrain_relief, seed=args.seed,
        distortion=args.distortion, blunders=args.blunders, force=args.force,
        **irregular,
    )
    _say(f"generated {info['path']}: {info['photos']} photos in {info['strips']} strips, "
         f"{info['points']} points ({info['control_points']} control, "
         f"{info['check_points']} check), {info['observations']} image observations")
    return 0


def cmd_order(args):
    from .ordering import order_project

    r = order_project(args.project, args.method, memory=args.memory, solver=args.solver,
                      leaf_stations=args.leaf_stations, page_stations=args.page_stations)
    _report_exclusions(r.excluded_points, r.excluded_stations, r.n_excluded_points,
                       r.n_excluded_stations)
    cands = ", ".join(f"{k} {v}" for k, v in r.candidates.items())
    _say(f"band width before: {r.band_width_before}")
    if r.solver == "tree":
        t = r.tree
        _say(f"solver: tree ({t['method']} bisection): {t['nodes']} nodes, {t['leaves']} "
             f"leaves, depth {t['depth']}, largest front {t['largest_front']} stations "
             f"({t['largest_front_bytes'] / 2**20:.1f} MiB), fronts in core "
             f"{t['fronts_bytes'] / 2**20:.1f} MiB (tiled beyond adjust's --memory), factor "
             f"{t['factor_bytes'] / 2**20:.1f} MiB, {t['flops'] / 1e9:.2f} GFlop")
    else:
        _say(f"band width after:  {r.band_width}  ({r.ordering}; candidates: {cands})")
    if r.predicted:
        names = {"tree_window": "tree (scaled from a window of the band order)"}
        pred = ", ".join(f"{names.get(k, k)} {v:.3g} s" for k, v in r.predicted.items())
        _say(f"predicted factorisation: {pred}")
    return 0


def cmd_init(args):
    from .init import initialise

    r = initialise(args.project, method=args.method)
    _say(f"placed {r.photos_placed} of {r.photos} photos and intersected "
         f"{r.points_intersected} points ({r.method} start, {r.sweeps} sweeps of resection "
         f"and intersection); next: sapgo adjust {args.project}")
    if r.photos_not_placed:
        _warn(f"{r.photos - r.photos_placed} photo(s) are not connected to two points of "
              f"known X, Y and keep their values: ids "
              f"{', '.join(map(str, r.photos_not_placed))}")
    if r.points_not_intersected:
        _warn(f"{r.points_not_intersected} point(s) could not be intersected (fewer than two "
              f"rays, or rays under 1 degree) and keep approximate values")
    return 0


def cmd_import(args):
    if args.append and args.format != "text":
        raise ParameterError(f"--append applies to the text files' import; --format "
                             f"{args.format} makes a new project (--force replaces one)")
    if args.sigma_image is not None and args.format not in ("colmap", "opensfm"):
        raise ParameterError("--sigma-image applies to --format colmap and opensfm (a "
                             "cameras file gives each camera's sigma_image, a BAL problem "
                             "has 1 pixel)")
    if args.reconstruction is not None and args.format != "opensfm":
        raise ParameterError("--reconstruction applies to --format opensfm")
    if args.format == "photomodeler":
        from .formats.photomodeler import import_photomodeler

        if len(args.paths) != 2:
            raise ParameterError("--format photomodeler takes the export and the project to "
                                 "create: sapgo import --format photomodeler export.txt "
                                 "block.h5")
        if args.merge_duplicates:
            raise ParameterError("--merge-duplicates does not apply to --format photomodeler "
                                 "(its marks agreeing within 3 sigma are averaged; others "
                                 "are an error naming both lines)")
        r = import_photomodeler(args.paths[0], args.paths[1], force=args.force)
        for w in r.get("warnings", ()):
            _warn(w)
        datum = ("a free network" if r["free"] else
                 f"{r['control_points']} control points")
        _say(f"imported {r['path']}: {r['photos']} photos, {r['cameras']} camera(s) (held; "
             f"the measurements freed of PhotoModeler's lens distortion), {r['points']} "
             f"points, {r['observations']} image observations; {datum}")
        return 0
    if args.format == "opensfm":
        from .formats.opensfm import import_opensfm

        if len(args.paths) != 2:
            raise ParameterError("--format opensfm takes the dataset (its directory, or its "
                                 "reconstruction.json) and the project to create: sapgo "
                                 "import --format opensfm DATASET block.h5")
        r = import_opensfm(args.paths[0], args.paths[1], index=args.reconstruction or 0,
                           sigma_image=1.0 if args.sigma_image is None else args.sigma_image,
                           force=args.force, merge_duplicates=args.merge_duplicates)
        for w in r.get("warnings", ()):
            _warn(w)
        many = (f" (reconstruction {r['index']} of {r['reconstructions']})"
                if r["reconstructions"] > 1 else "")
        _say(f"imported {r['path']}{many}: {r['cameras']} cameras (held), {r['photos']} "
             f"photos, {r['points']} points, {r['observations']} image observations "
             f"(pixels); a free network; OpenSfM's mean reprojection error "
             f"{r['mean_error_px']:.4g} px")
        return 0
    if args.format in ("bal", "bundler"):
        if args.format == "bal":
            from .formats.bal import import_bal as load
        else:
            from .formats.bundler import import_bundler as load
        name, example = {"bal": ("the BAL file", "problem.txt"),
                         "bundler": ("the Bundler file", "bundle.out")}[args.format]
        if len(args.paths) != 2:
            raise ParameterError(f"--format {args.format} takes {name} and the project to "
                                 f"create: sapgo import --format {args.format} {example} "
                                 f"block.h5")
        r = load(args.paths[0], args.paths[1], force=args.force,
                 intrinsics="fixed" if args.fixed_intrinsics else "adjusted",
                 merge_duplicates=args.merge_duplicates)
        for w in r.get("warnings", ()):
            _warn(w)
        skipped = (f" ({r['not_reconstructed']} camera(s) not reconstructed left out)"
                   if r.get("not_reconstructed") else "")
        _say(f"imported {r['path']}: {r['photos']} photos (one camera each, f, k1, k2 "
             f"{'held' if args.fixed_intrinsics else 'adjusted'}){skipped}, {r['points']} "
             f"points, {r['observations']} image observations (pixels); a free network; "
             f"initial cost {r['initial_cost']:.6e}")
        return 0
    if args.format == "colmap":
        return _import_colmap(args)
    from .ingest import import_text, summary_text

    if len(args.paths) != 1:
        raise ParameterError("text import takes one project to create (the files are given "
                             "with --cameras, --photos, --measurements, ...)")
    summary = import_text(
        args.paths[0], cameras=args.cameras, photos=args.photos,
        measurements=args.measurements, control=args.control, angles=args.angles,
        memory=args.memory, append=args.append, force=args.force, priors=args.priors,
        prior_covariances=args.prior_covariances, crs=args.crs, orientation=args.orientation,
        photos_matrix=args.photos_matrix, rotation=args.rotation,
        image_frames=args.image_frames, axis_order=args.axis_order,
        merge_duplicates=args.merge_duplicates,
        additional_parameters=args.additional_parameters,
    )
    for w in summary["warnings"]:
        _warn(w)
    _say(summary_text(summary))
    return 0


def _int_list(text, option):
    try:
        return tuple(int(x) for x in text.replace(",", " ").split())
    except ValueError:
        raise ParameterError(f"{option} {text!r}: a list of integer ids, e.g. 1,3") from None


def _import_colmap(args):
    from .formats.colmap import import_colmap

    if len(args.paths) != 2:
        raise ParameterError("--format colmap takes the model's directory and the project to "
                             "create: sapgo import --format colmap MODEL_DIR block.h5")
    given = [o for o, v in (("--cameras", args.cameras), ("--photos", args.photos),
                            ("--photos-matrix", args.photos_matrix),
                            ("--measurements", args.measurements), ("--priors", args.priors),
                            ("--prior-covariances", args.prior_covariances),
                            ("--append", args.append), ("--fixed-intrinsics",
                                                        args.fixed_intrinsics)) if v]
    if given:
        raise ParameterError(f"--format colmap does not take {', '.join(given)} (the model "
                             f"holds the cameras, photos and measurements; --control adds "
                             f"control)")
    r = import_colmap(args.paths[0], args.paths[1], control=args.control, crs=args.crs,
                      sigma_image=1.0 if args.sigma_image is None else args.sigma_image,
                      force=args.force, memory=args.memory)
    for w in r["warnings"]:
        _warn(w)
    models = ", ".join(f"{n} {m}" for m, n in r["camera_models"].items())
    kinds = ", ".join(f"{n} {k}" for k, n in r["points_by_kind"].items() if n)
    _say(f"imported {r['path']}: {r['cameras']} camera(s) ({models}; intrinsics held), "
         f"{r['photos']} photo(s), {r['points']} point(s) ({kinds}), {r['observations']} "
         f"image observations (pixels), {r['points2D_without_3D']} 2D points without a 3D "
         f"point kept; mean reprojection error {r['mean_reprojection_error']:.4f} px")
    if r["y_scaled_cameras"]:
        _say(f"{r['y_scaled_cameras']} camera(s) with fx != fy: image y scaled by fx/fy")
    if r["free"]:
        _say("no control: a free network (adjusted by Levenberg-Marquardt)")
    elif r["aligned"]:
        a = r["aligned"]
        _say(f"model aligned to {a['points']} full control points ({r['frame']}): scale "
             f"{a['scale']:.6g}, rotation {a['rotation_deg']:.4f} deg, RMS {a['rms']:.4g} m")
    return 0


def cmd_adjust(args):
    from .adjust import Options, adjust
    from .project import Project

    opts = Options(
        max_iterations=args.max_iterations,
        tol_position=args.tol_position,
        tol_angle=args.tol_angle * math.pi / (180 * 3600),
        tol_sigma0=args.tol_sigma0,
        ordering=args.ordering,
        solver=args.solver,
        keep_scratch=args.keep_scratch,
        resume=args.resume,
        memory=args.memory,
        progress=False if args.no_progress else None,
        robust=args.robust,
        robust_threshold_um=args.robust_threshold,
        snooping=args.snooping or args.snooping_batch, snooping_batch=args.snooping_batch,
        snooping_alpha=args.alpha, reset_rejections=args.reset_rejections,
        precision=args.precision,
        factor_storage=args.factor_storage,
        work_files=args.work_files,
        page_stations=args.page_stations,
        method=args.method,
        tol_cost=args.tol_cost,
        calibrate=args.calibrate or (),
        calibrate_cameras=(None if args.calibrate_cameras is None else
                           _int_list(args.calibrate_cameras, "--calibrate-cameras")),
        calibrate_per_photo=args.calibrate_per_photo or (),
        fix=tuple(_datum_fixes(args.datum)), datum=_datum_choice(args.datum),
    )
    if args.plots:  # before a long run: matplotlib is there
        from .plots import check_matplotlib

        check_matplotlib()
    with Project(args.project) as p:
        ordered = p.ordered
    from .solve.distributed import cluster

    if (args.workers or args.scheduler) and args.solver == "band":
        raise SapgoError("--workers and --scheduler distribute the partition tree: not with "
                         "--solver band")
    if args.workers is not None and args.workers < 1:
        raise SapgoError(f"--workers {args.workers}: give 1 or more worker processes")
    try:
        with cluster(args.workers, args.scheduler) as client:
            if client is not None:
                opts.client = client
                if opts.solver == "auto":
                    opts.solver = "tree"
            summary = adjust(args.project, opts)
    except KeyboardInterrupt:
        from .work import work_path

        if (work_path(args.project) / "checkpoint.json").exists():
            print(f"sapgo: interrupted; the last completed iteration is kept: continue with "
                  f"'sapgo adjust --resume {args.project}'", file=sys.stderr)
        else:   # (a run in memory: --work-files)
            print(f"sapgo: interrupted; the run was held in memory and kept no checkpoint: "
                  f"{args.project} is as it was (run again, or with --work-files always to "
                  f"keep every iteration)", file=sys.stderr)
        return 130
    if not ordered:
        _report_exclusions(summary.excluded_points, summary.excluded_stations,
                           summary.n_excluded_points, summary.n_excluded_stations)
    if not summary.converged:
        _warn(summary.termination)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(summary.to_json() + "\n")
    if not args.quiet:
        _say(summary.full_report())
    _outputs(args)
    return 0


def _outputs(args):
    """The CSV tables and plots asked for by --csv and --plots."""
    if args.csv:
        from .tables import write_tables

        r = write_tables(args.project, args.csv)
        _say(f"wrote {', '.join(f'{n} {k}' for k, n in r['counts'].items())} to "
             f"{args.csv} (CSV)")
    if args.plots:
        from .plots import write_plots

        r = write_plots(args.project, args.plots)
        _say(f"wrote {len(r)} plots to {args.plots}: {', '.join(Path(x).name for x in r)}")


def cmd_report(args):
    import dataclasses

    from .errors import DataError
    from .project import Project
    from .report import Summary

    with Project(args.project) as p:
        if not p.has_solution or p.file["solution"].attrs.get("state") != "adjusted":
            raise DataError(f"{args.project}: the project has no adjusted solution: run "
                            f"'sapgo adjust' first")
        data = json.loads(p.file["solution/report"][()])
    if args.json:
        _say(json.dumps(data, indent=2))
    elif not args.quiet:
        names = {f.name for f in dataclasses.fields(Summary)}
        _say(Summary(**{k: v for k, v in data.items() if k in names}).full_report())
    _outputs(args)
    return 0


def cmd_export(args):
    from .formats import export_adjusted, export_text

    if args.pixel_size is not None and args.format not in ("colmap", "photomodeler"):
        raise ParameterError("--pixel-size applies to --format colmap and photomodeler")
    if args.format == "colmap":
        from .formats.colmap import export_colmap

        r = export_colmap(args.project, args.directory, adjusted=args.adjusted,
                          pixel_size=args.pixel_size)
        models = ", ".join(f"{n} {m}" for m, n in r["models"].items())
        _say(f"wrote {'the adjusted' if args.adjusted else 'the input'} COLMAP model "
             f"{args.directory}: {r['cameras']} cameras ({models}), {r['images']} images, "
             f"{r['points']} points, {r['observations']} observations")
    elif args.format == "bal":
        from .formats.bal import export_bal

        r = export_bal(args.project, args.directory, adjusted=args.adjusted)
        _say(f"wrote {'the adjusted' if args.adjusted else 'the input'} BAL problem "
             f"{args.directory}: {r['cameras']} cameras, {r['points']} points, "
             f"{r['observations']} observations")
    elif args.format == "photomodeler":
        from .formats.photomodeler import export_photomodeler

        r = export_photomodeler(args.project, args.directory, adjusted=args.adjusted,
                                pixel_size=args.pixel_size)
        part = (f"; {r['partial_control']} horizontal or vertical control point(s) written "
                f"as object points only" if r["partial_control"] else "")
        _say(f"wrote {'the adjusted' if args.adjusted else 'the input'} PhotoModeler export "
             f"{args.directory}: {r['photos']} photos, {r['points']} points "
             f"({r['control_points']} control), {r['observations']} marked points{part}")
    elif args.format == "opensfm":
        from .formats.opensfm import export_opensfm

        r = export_opensfm(args.project, args.directory, adjusted=args.adjusted)
        _say(f"wrote {'the adjusted' if args.adjusted else 'the input'} OpenSfM dataset "
             f"{args.directory}: {r['cameras']} cameras, {r['photos']} shots, "
             f"{r['points']} points, {r['observations']} observations")
    elif args.format == "bundler":
        from .formats.bundler import export_bundler

        r = export_bundler(args.project, args.directory, adjusted=args.adjusted)
        _say(f"wrote {'the adjusted' if args.adjusted else 'the input'} Bundler file "
             f"{args.directory}: {r['cameras']} cameras ({r['photos']} photos), "
             f"{r['points']} points, {r['observations']} observations")
    elif args.adjusted:
        r = export_adjusted(args.project, args.directory, angles=args.angles,
                            orientation=args.orientation, rotation=args.rotation)
        _say(f"wrote {r['counts']['photos']} adjusted photos and {r['counts']['points']} "
             f"points to {args.directory}")
    else:
        r = export_text(args.project, args.directory, angles=args.angles,
                        rotation=args.rotation)
        _say(f"wrote {', '.join(f'{n} {k}' for k, n in r['counts'].items())} to "
             f"{args.directory}")
    return 0


def _datum_fixes(values):
    """``--datum`` values of the kind ``fix:IDS:PARAMS``."""
    for v in values:
        if v.lower().startswith("fix:"):
            yield v
        elif v.lower() not in ("control", "priors", "free"):
            raise ParameterError(f"--datum {v!r}: expected control, priors, free or "
                                 f"fix:IDS:PARAMS (e.g. fix:101:omega,phi,kappa,X,Y,Z)")


def _datum_choice(values):
    """The ``--datum`` value control, priors or free (at most one), or None."""
    words = [v.lower() for v in values if not v.lower().startswith("fix:")]
    if len(set(words)) > 1:
        raise ParameterError(f"--datum {' and '.join(sorted(set(words)))}: choose one")
    return words[0] if words else None


def cmd_info(args):
    import numpy as np

    from .project import KIND_NAMES, Project

    with Project(args.project) as p:
        kinds = {}
        for a, b in p.chunks("points"):
            values, counts = np.unique(p.read_field("points", "kind", a, b),
                                       return_counts=True)
            for k, n in zip(values, counts):
                name = KIND_NAMES.get(int(k), f"unknown kind {int(k)}")
                kinds[name] = kinds.get(name, 0) + int(n)
        info = {
            "path": str(p.path),
            "schema_version": int(p.attr("schema_version")),
            "created": p.attr("created"),
            "cameras": p.n_cameras,
            "stations": p.n_stations,
            "points": p.n_points,
            "points_by_kind": kinds,
            "observations": p.n_observations,
            "station_priors": p.n_priors,
            "frame": p.frame().describe(),
            "ordered": p.ordered,
            "ordering": p.attr("ordering") if p.ordered else None,
            "band_width": p.band_width if p.ordered else None,
            "solver": p.solver if p.ordered else None,
            "tree": _tree_info(p),
            "has_truth": p.has_truth,
            "adjusted": p.has_solution and p.file["solution"].attrs.get("state") == "adjusted",
        }
    if args.json:
        _say(json.dumps(info, indent=2))
        return 0
    for k, v in info.items():
        if k == "band_width" and not info["ordered"]:
            v = NOT_ORDERED
        elif v is None:
            v = "-"
        elif isinstance(v, dict):
            v = ", ".join(f"{a} {b}" for a, b in v.items()) or "-"
        _say(f"{k:16s} {v}")
    return 0


#: ``sapgo info``'s word for the band width of a project not yet ordered.
NOT_ORDERED = "not ordered yet (sapgo order, or adjust orders it)"


def _tree_info(p):
    from .errors import ProjectFormatError

    try:
        t = p.tree()
    except ProjectFormatError as exc:
        return f"stale ({exc}); run 'sapgo order'"
    if t is None:
        return None
    k = 9 if p.attr("station_intrinsics", "") == "adjusted" else 6
    f = t.figures(k)
    return {key: f[key] for key in ("method", "nodes", "leaves", "depth", "largest_front",
                                    "fronts_bytes", "factor_bytes", "flops")}


def _fraction(text, option):
    """An overlap given as a fraction (0.6) or a percentage (60)."""
    try:
        v = float(text)
    except ValueError:
        raise ParameterError(f"{option} {text!r}: a percentage (60) or a fraction (0.6)") \
            from None
    return v / 100.0 if v > 1.0 else v


def _design_lists(args):
    """The irregular design's per-strip lists (--strip-lengths, --strip-starts, --scales)."""
    out = {}
    for key, text in (("lengths", args.strip_lengths), ("starts", args.strip_starts),
                      ("scales", args.scales)):
        try:
            out[key] = None if text is None else [float(x) for x in
                                                  text.replace(",", " ").split()]
        except ValueError:
            out[key] = [math.nan]
        if out[key] is not None and not all(math.isfinite(v) for v in out[key]):
            option = "--scales" if key == "scales" else f"--strip-{key}"
            raise ParameterError(f"{option} {text!r}: a finite number per strip, e.g. "
                                 f"10,8,12")
    if args.shift is not None and not math.isfinite(args.shift):
        raise ParameterError(f"--shift {args.shift}: a finite fraction of the base")
    if out["lengths"] is not None:
        if any(v != int(v) for v in out["lengths"]):
            raise ParameterError("--strip-lengths takes whole numbers of photos, e.g. 10,8,12")
        out["lengths"] = [int(v) for v in out["lengths"]]
    return out


def _design_arguments(parser):
    """The options of an irregular flight design (sapgo plan and sapgo generate)."""
    parser.add_argument("--shift", type=float,
                        help="irregular design: every other strip shifted by this fraction of "
                             "the base (default 0)")
    parser.add_argument("--strip-lengths", metavar="N,N,...",
                        help="irregular design: photos of each strip (default: "
                             "--photos-per-strip each)")
    parser.add_argument("--strip-starts", metavar="X,X,...",
                        help="irregular design: where each strip starts, in bases (default 0 "
                             "each)")
    parser.add_argument("--scales", metavar="C,C,...",
                        help="irregular design: each strip's photo scale relative to the others "
                             "(its footprint's side; default 1 each)")


def cmd_plan(args):
    from .plan import design_network, evaluate, project_network, write_pattern

    design = [args.strips, args.photos_per_strip, args.shift, args.strip_lengths,
              args.strip_starts, args.scales]
    if args.project and any(v is not None for v in design):
        raise ParameterError("sapgo plan takes either a project or a flight design "
                             "(--strips, --photos-per-strip, --shift, --strip-lengths, "
                             "--strip-starts, --scales), not both")
    design = design[:2]
    if args.plot_ordering == "adjust" and not args.project:
        raise ParameterError("--plot-ordering adjust draws the order sapgo order gives a "
                             "project: give a project")
    if args.project:
        net = project_network(args.project)
        source = {"project": str(args.project)}
    else:
        if None in design:
            raise ParameterError("a flight design needs --strips and --photos-per-strip "
                                 "(or give a project)")
        forelap = _fraction(args.forelap, "--forelap")
        sidelap = _fraction(args.sidelap, "--sidelap")
        lists = _design_lists(args)
        net = design_network(args.strips, args.photos_per_strip, forelap, sidelap,
                             args.units, args.cross, args.model_step, args.shift or 0.0,
                             lists["lengths"], lists["starts"], lists["scales"])
        source = {"design": {"strips": args.strips, "photos_per_strip": args.photos_per_strip,
                             "forelap": forelap, "sidelap": sidelap, "units": args.units,
                             "cross_models": args.cross}}
    result = evaluate(net, timing=not args.no_timing)
    result.update(source)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    if args.plot:
        write_pattern(net, args.plot, args.plot_ordering or result["recommended"])
    unit = f"{net.kind} ({net.params} parameters)"
    _say(f"{net.n} {unit}, {len(net.s)} joined pairs")
    head = (f"{'ordering':14s} {'T':>7s} {'m':>9s} {'W':>6s} {'D':>6s} {'F.I.':>10s} "
            f"{'band MB':>9s} {'envelope MB':>12s} {'sparse MB':>10s} {'solve s':>9s}")
    _say(head)
    for name, r in result["orderings"].items():
        b = r["storage_bytes"]
        if "predicted_solve_s" not in r:
            t = f"{'-':>9s}"
        else:  # (<=: not timed, more than ten times the least work: an upper bound)
            bound = "<=" if r["timed_units"] == 0 else ""
            t = f"{bound + format(r['predicted_solve_s'], '.3f'):>9s}"
        mark = " *" if name == result["recommended"] else ""
        _say(f"{name:14s} {r['dimension']:7d} {r['nonzero_blocks']:9d} "
             f"{r['band_width_m']:6d} {r['band_width_b']:6d} {r['fill_in_blocks']:10d} "
             f"{b['band'] / 1e6:9.2f} {b['envelope'] / 1e6:12.2f} {b['sparse'] / 1e6:10.2f} "
             f"{t}{mark}")
    if "adjust" in result:
        a = result["adjust"]
        t = f", predicted solve {a['predicted_solve_s']:.3f} s" if "predicted_solve_s" in a \
            else ""
        if a.get("solver") == "tree":
            _say(f"sapgo order will choose the partition tree ({a['ordering']}){t}")
        else:
            _say(f"sapgo order will choose {a['ordering']}: band width W "
                 f"{a['band_width_m']}, fill-in {a['fill_in_blocks']} blocks{t}")
    tr = result.get("tree")
    if tr:
        _say(f"partition tree ({tr['method']}): {tr['nodes']} nodes, depth {tr['depth']}, "
             f"largest front {tr['largest_front']} units, fronts in core "
             f"{tr['fronts_bytes'] / 2**20:.1f} MiB (tiled beyond adjust's --memory), factor "
             f"{tr['factor_bytes'] / 2**20:.1f} MiB, {tr['flops']:.3g} flops, predicted "
             f"solve {tr['predicted_solve_s']:.3f} s")
    _say(f"recommended: {result['recommended']} (the least work: a band ordering, or the "
         f"partition tree; T units, "
         f"m non-zero blocks, W band width in blocks, D in whole sub-matrices of lines, F.I. "
         f"fill-in blocks; solve s <=: not timed, over ten times the least work, a bound)")
    return 0


def _output_options(parser):
    parser.add_argument("--csv", metavar="DIR",
                        help="write photos.csv, points.csv and observations.csv (residuals, "
                             "precision, redundancy numbers, flags) into DIR (default: no "
                             "tables)")
    parser.add_argument("--plots", metavar="DIR",
                        help="write the plots (block layout, residuals per camera, check-point "
                             "errors, reduced-matrix pattern) into DIR as PNG; needs "
                             "matplotlib (pip install 'sapgo[plot]'; default: no plots)")


def build_parser():
    from .ordering import ORDERINGS

    ap = argparse.ArgumentParser(
        prog="sapgo",
        description="Out-of-core bundle block adjustment (after the 1974 SAPGO program).",
    )
    ap.add_argument("--version", action="version", version=f"sapgo {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    g = sub.add_parser("generate", help="generate a synthetic block (SAPGO-P presets)",
                       description="Generate a SAPGO-P block with known truth into a new "
                                   "project file. Without --preset the parameters below "
                                   "describe the block (defaults: SAPGO-P data set 1).")
    from .generate import ALL_PRESETS

    g.add_argument("output", help="project file to create (e.g. data/generated/p3.h5)")
    g.add_argument("--preset", choices=ALL_PRESETS,
                   help="a block of seeds/002: SAPGO-P (Table 2) or SAPGO-MFL (Table 5); the "
                        "options below change a SAPGO-P preset's values (default: none, "
                        "SAPGO-P data set 1 with the options' values)")
    g.add_argument("--strips", type=int, metavar="N",
                   help="number of strips (default 4, or the preset's)")
    g.add_argument("--photos-per-strip", type=int, metavar="N",
                   help="photos in each strip (default 25, or the preset's)")
    g.add_argument("--pattern", type=int, choices=(9, 25),
                   help="points per photo, 3 x 3 or 5 x 5 (default 9, or the preset's)")
    g.add_argument("--points-per-photo", type=int, metavar="N",
                   help="tie points from a random texture instead of the pattern: about N "
                        "on each photo, each measured on every photo that covers it, as "
                        "image matching gives (4-5000; default: the pattern)")
    g.add_argument("--control-points", type=int, metavar="N",
                   help="number of full control points; the other known points are check "
                        "points (default 16, or the preset's)")
    g.add_argument("--forelap", type=float,
                   help="forelap, a fraction (default 0.6, or the preset's)")
    g.add_argument("--sidelap", type=float,
                   help="sidelap, a fraction (default 0.2, or the preset's)")
    g.add_argument("--sigma-image", type=float, metavar="UM",
                   help="perturbation and standard error of the image coordinates, um "
                        "(default 6)")
    g.add_argument("--station-position-perturbation", type=float, metavar="M",
                   help="perturbation of the photos' approximate positions, m (default 5)")
    g.add_argument("--station-angle-perturbation", type=float, metavar="ARCSEC",
                   help="perturbation of the photos' approximate angles, arc seconds "
                        "(default 20)")
    g.add_argument("--control-perturbation", type=float, metavar="M",
                   help="perturbation of the control points' known coordinates, m (default "
                        "0.001)")
    g.add_argument("--terrain-relief", type=float, metavar="M",
                   help="standard deviation of terrain heights, m (default 100; 30 for an "
                        "irregular design)")
    g.add_argument("--distortion", type=_five_numbers, metavar="K1,K2,K3,P1,P2",
                   help="the camera's lens distortion (Brown; mm^-2, mm^-4, mm^-6, mm^-1, "
                        "mm^-1), applied to the simulated image coordinates; write it with "
                        "'=' when it starts with a minus: --distortion=-2e-8,0,0,1e-6,0 "
                        "(default none)")
    g.add_argument("--blunders", type=int, metavar="N",
                   help="plant N blunders of 30 to 100 um in random image observations (listed "
                        "in /truth/blunders; default 0)")
    g.add_argument("--seed", type=int, help="random seed (default 1)")
    g.add_argument("--force", action="store_true",
                   help="replace an existing project file at OUTPUT (default: refuse to)")
    _design_arguments(g)
    g.set_defaults(func=cmd_generate)

    o = sub.add_parser("order", help="order stations and points to minimise the band width",
                       description="Order a project's stations (photos) and points for the "
                                   "solver: a band ordering of the least band width, or a "
                                   "partition tree (nested dissection), whichever is predicted "
                                   "to factor faster (--solver auto). Points seen on fewer "
                                   "than 2 photos and photos with fewer than 3 such points are "
                                   "left out of the adjustment (they stay in the project). "
                                   "sapgo adjust orders an unordered project itself.")
    o.add_argument("project", help="the project file (e.g. block.h5)")
    o.add_argument("--method", default="best", choices=ORDERINGS, metavar="ORDERING",
                   help="the band's station order: best (default: the least band width of "
                        "all), across_strip, down_strip, diagonal, spiral, "
                        "reverse_cuthill_mckee, across_strip_by_position, sweep_0 ... "
                        "sweep_165 (every 15 degrees)")
    o.add_argument("--memory", default=None, metavar="SIZE",
                   help="memory budget of the external sorts, e.g. 256M or 2G (default 512M)")
    o.add_argument("--solver", choices=("auto", "band", "tree"), default="auto",
                   help="order for the band solver (long strips), for the partition tree "
                        "(nested dissection: square, irregular and unordered blocks), or "
                        "auto (default): the one of the smaller predicted factorisation time")
    o.add_argument("--leaf-stations", type=int, default=None, metavar="N",
                   help="the partition tree's largest leaf (default 24 stations)")
    o.add_argument("--page-stations", type=int, default=None, metavar="N",
                   help="above N photos keep the per-photo vectors and the station graph in "
                        "memory-mapped scratch files beside the project, their pages "
                        "returned to the page cache as the passes move on (default 2000000; "
                        "0: always)")
    o.set_defaults(func=cmd_order)

    ini = sub.add_parser("init", help="starting values of a block's photos and points from "
                                      "its control (aerial or convergent)",
                         description="Starting values of a block from its control: a "
                                     "near-vertical (aerial) block's photos as vertical "
                                     "photos from a planimetric block adjustment over the "
                                     "control's X, Y; a convergent block's photos resected "
                                     "directly from known points, propagated through the "
                                     "block; the points intersected, then sweeps of "
                                     "resection and intersection. The project's "
                                     "approximations are replaced (a stored solution is "
                                     "dropped). Then: sapgo adjust.")
    ini.add_argument("project", help="the project file (e.g. block.h5)")
    ini.add_argument("--method", choices=("auto", "vertical", "resection"), default="auto",
                     help="vertical: aerial blocks, from a planimetric block adjustment; "
                          "resection: convergent (close-range) blocks, photos resected "
                          "directly from 6 or more known points not in a plane and the "
                          "points intersected, in turns through the block; auto (default): "
                          "resection when a photo sees 6 known points that span space")
    ini.set_defaults(func=cmd_init)

    m = sub.add_parser("import", help="import a block: text files (cameras, photos, image "
                                      "measurements, control), BAL, Bundler, COLMAP, OpenSfM "
                                      "or PhotoModeler",
                       description="Import a block from whitespace-separated text files into "
                                   "a new project (formats: docs/formats.md), a BAL problem "
                                   "(--format bal FILE OUTPUT), a Bundler file (--format "
                                   "bundler bundle.out OUTPUT), an OpenSfM dataset "
                                   "(--format opensfm DIR OUTPUT) or a COLMAP text model "
                                   "(--format colmap MODEL_DIR OUTPUT [--control FILE]). "
                                   "Each file option may be "
                                   "repeated. The measurements are sorted within the memory "
                                   "budget, so their files may be in any order.")
    m.add_argument("paths", nargs="+", metavar="[FILE] OUTPUT",
                   help="the project file to create (e.g. block.h5); with --format bal or "
                        "bundler the file first, with --format colmap the model's directory "
                        "first")
    m.add_argument("--format", choices=("text", "bal", "bundler", "colmap", "opensfm",
                                        "photomodeler"),
                   default="text",
                   help="text (default: the files below), bal (a 'Bundle Adjustment in the "
                        "Large' problem: one camera per photo whose f, k1, k2 are adjusted "
                        "with it, pixels, a free network adjusted by Levenberg-Marquardt), "
                        "bundler (a Bundler v0.3/v0.4 bundle.out: the same camera model), "
                        "opensfm (reconstruction.json and tracks.csv: shared cameras, held; "
                        "pixels; a free network), photomodeler (PhotoModeler's text export "
                        "as DBAT reads it: the camera held, its backward distortion applied "
                        "to the measurements) or "
                        "colmap (COLMAP's text model: cameras.txt, images.txt, points3D.txt; "
                        "pixels; a free network, or with --control aligned to the control "
                        "and adjusted with it)")
    m.add_argument("--sigma-image", type=float, metavar="PX",
                   help="with --format colmap or opensfm: standard error of the image "
                        "coordinates, pixels (default 1)")
    m.add_argument("--reconstruction", type=int, metavar="N",
                   help="with --format opensfm: which reconstruction of the file (default 0, "
                        "the first)")
    m.add_argument("--fixed-intrinsics", action="store_true",
                   help="with --format bal or bundler: hold each photo's f, k1, k2 fixed "
                        "(default: adjusted with the photo)")
    m.add_argument("--cameras", action="append", default=[], metavar="FILE",
                   help="id focal_length x0 y0 format_x format_y sigma_image [k1 k2 k3 p1 p2 "
                        "[b1 b2 [forward|backward]]] (mm; the distortion model: forward, "
                        "added to the ideal point, the default; backward, correcting the "
                        "measured point as PhotoModeler and DBAT; repeatable; default none)")
    m.add_argument("--photos", action="append", default=[], metavar="FILE",
                   help="id camera strip omega phi kappa X Y Z (angles: --angles; m; "
                        "repeatable; default none)")
    m.add_argument("--photos-matrix", action="append", default=[], metavar="FILE",
                   help="photos with a rotation matrix: id camera strip m11 m12 m13 m21 m22 "
                        "m23 m31 m32 m33 X Y Z (object to image, row by row; repeatable; "
                        "default none)")
    m.add_argument("--measurements", action="append", default=[], metavar="FILE",
                   help="photo point x y [sigma] (mm; sigma 0 or missing = the camera's; "
                        "repeatable; default none)")
    m.add_argument("--control", action="append", default=[], metavar="FILE",
                   help="point X Y Z sX sY sZ [full|horizontal|vertical|check] (m; '-' = "
                        "unknown; with --format colmap the points are POINT3D_IDs; "
                        "repeatable; default: no control, a free network)")
    m.add_argument("--priors", action="append", default=[], metavar="FILE",
                   help="exposure-station priors (GNSS/INS, orbit): photo omega phi kappa X Y "
                        "Z s_omega s_phi s_kappa sX sY sZ (angle sigmas in arc seconds, m; 0 "
                        "or '-' = unconstrained; repeatable; default none)")
    m.add_argument("--prior-covariances", action="append", default=[], metavar="FILE",
                   help="priors with a full covariance: photo omega phi kappa X Y Z and the "
                        "21 terms c11 c12 ... c16 c22 ... c66 of its upper triangle (arc "
                        "seconds, m; repeatable; default none)")
    m.add_argument("--angles", choices=("deg", "gon", "rad"), default="deg",
                   help="unit of omega, phi, kappa in the photos and priors files (default "
                        "deg; in deg they may also be written in degrees, minutes and "
                        "seconds: -12:34:56.7, 12d34m56.7s or 12°34'56.7\")")
    m.add_argument("--axis-order", choices=("en", "ne"), default="en",
                   help="the order of X and Y in the photos, control and priors files: en "
                        "easting (longitude) first (default), ne northing (latitude) first; "
                        "with a geographic --crs they may be written in degrees, minutes and "
                        "seconds (49:00:12.3N)")
    m.add_argument("--image-frames", action="append", default=[], metavar="FILE",
                   help="per camera, how its photos' measurements are given: camera unit "
                        "(mm|px) pixel_x pixel_y (um, '-' for mm) width height (in the unit) "
                        "origin (centre|topleft|bottomleft) y_axis (up|down) (default, and "
                        "cameras not listed: mm from the centre, y up)")
    m.add_argument("--additional-parameters", action="append", default=[], metavar="FILE",
                   help="per camera, an additional-parameter set of aerial triangulation: "
                        "camera set (ebner: Ebner's 12, gruen: Gruen's 44, none) base (mm, "
                        "or auto: 0.4 x the format's larger side) [a1 ... aN] (mm; default "
                        "0); adjusted with adjust --calibrate ap (see docs/formats.md)")
    m.add_argument("--rotation", choices=("opk", "pok", "kpo"), default="opk",
                   help="the order of the three angles in the photos' and priors' columns "
                        "and how they compose: opk omega-phi-kappa M = R3(k) R2(p) R1(o) "
                        "(default), pok phi-omega-kappa M = R3(k) R1(o) R2(p) (Y primary), "
                        "kpo kappa-phi-omega M = R1(o) R2(p) R3(k); the priors' angle "
                        "sigmas in the same order")
    m.add_argument("--crs", metavar="CRS",
                   help="coordinate reference system of the photos', control's and priors' X "
                        "Y Z: an EPSG or IAU code, WKT or PROJ string (EPSG:4978 geocentric, "
                        "EPSG:4979 longitude latitude height, EPSG:32632 UTM, IAU_2015:30100 "
                        "the Moon, ...); the block is then computed in the local tangent frame "
                        "at its centre (Earth) or selenocentric (Moon). Default: a local frame")
    m.add_argument("--orientation", choices=("tangent", "geocentric"), default="tangent",
                   help="with --crs: omega, phi, kappa relative to the local east-north-up "
                        "frame at each photo (default; GNSS/INS) or to the body-fixed axes")
    m.add_argument("--memory", default=None, metavar="SIZE",
                   help="memory budget of the external sorts, e.g. 256M or 2G (default 512M)")
    m.add_argument("--append", action="store_true",
                   help="add the files to an existing project (as if imported together; "
                        "default: a new project)")
    m.add_argument("--force", action="store_true",
                   help="replace an existing project (default: refuse to)")
    m.add_argument("--merge-duplicates", action="store_true",
                   help="average a point measured more than once on one photo even when the "
                        "measurements lie more than 3 sigma apart (default: such conflicting "
                        "duplicates are an error naming their lines; agreeing ones are merged "
                        "with a warning); text, BAL and Bundler files")
    m.set_defaults(func=cmd_import)

    a = sub.add_parser("adjust", help="adjust the block (orders it first if needed)",
                       description="Adjust the block by least squares: Gauss-Newton (or "
                                   "Levenberg-Marquardt) iterations of the reduced normal "
                                   "equations until the corrections fall below the "
                                   "tolerances; the solution, its precision and the report "
                                   "are stored in the project. An unordered project is "
                                   "ordered first (as sapgo order).")
    a.add_argument("project", help="the project file (e.g. block.h5)")
    a.add_argument("--json", metavar="PATH",
                   help="write the report as JSON to PATH (default: none)")
    a.add_argument("--max-iterations", type=int, default=None, metavar="N",
                   help="the most iterations (default 10, and 50 for a free network or "
                        "Levenberg-Marquardt; data snooping allows as many again after each "
                        "rejection)")
    a.add_argument("--tol-position", type=float, default=1e-4,
                   help="convergence: corrections of positions below this, m (default 1e-4)")
    a.add_argument("--tol-angle", type=float, default=0.1,
                   help="convergence: corrections of angles below this, arc seconds "
                        "(default 0.1)")
    a.add_argument("--tol-sigma0", type=float, default=1e-3,
                   help="convergence: relative change of sigma0 below this (default 1e-3)")
    a.add_argument("--ordering", default="best", choices=ORDERINGS, metavar="ORDERING",
                   help="the station order when the project is unordered (as sapgo order "
                        "--method): best (default), across_strip, down_strip, diagonal, "
                        "spiral, reverse_cuthill_mckee, across_strip_by_position, sweep_0 ... "
                        "sweep_165")
    a.add_argument("--solver", choices=("auto", "band", "tree"), default="auto",
                   help="the linear solver: band, tree (partition tree), or auto (default: "
                        "as the project is ordered; an unordered project is ordered for the "
                        "one of the smaller predicted time). A project ordered for the other "
                        "solver is ordered again first")
    a.add_argument("--workers", type=int, metavar="N",
                   help="build and factor the partition tree's subtrees on N worker "
                        "processes (a Dask LocalCluster for the run; needs sapgo[dask]; "
                        "default: threads of this process)")
    a.add_argument("--scheduler", metavar="ADDRESS",
                   help="the same on an existing Dask cluster (tcp://host:port); its workers "
                        "must see the project and its work directory at the same paths; "
                        "default: none)")
    a.add_argument("--robust", choices=("huber", "cauchy"),
                   help="robust estimation of the image observations: least squares first, "
                        "then reweighted every iteration from the standardised residuals "
                        "(control and priors are not); cauchy is the stronger (default: "
                        "none, least squares)")
    a.add_argument("--robust-threshold", type=float, default=30.0, metavar="UM",
                   help="threshold of the robust weights, um of standardised image residual "
                        "(the residual divided by the square root of its redundancy number; "
                        "default 30, five sigmas of a 6 um camera)")
    a.add_argument("--snooping", action="store_true",
                   help="Baarda's data snooping: reject the observation with the largest "
                        "normalised residual above the critical value and adjust again, until "
                        "none is left (rejected observations are flagged, not deleted; "
                        "default: no snooping)")
    a.add_argument("--factor-storage", choices=("auto", "core", "file", "replay"),
                   default="auto",
                   help="the band's factor between the factorisation and the passes that read "
                        "it back: core (in memory, nothing written), file (factor.bin, 12 KB "
                        "a photo at band width 42), replay (no factor file: each segment "
                        "refactored from its rows built again, scratch growing with the "
                        "band, not the photos) or auto (core up to a quarter of --memory, "
                        "default 1 GiB; replay beyond half the machine's memory or nine "
                        "tenths of the free disk; else file; the default)")
    a.add_argument("--work-files", choices=("auto", "always", "never"), default="auto",
                   help="the run's scratch: always (NAME.h5.work beside the project, "
                        "checkpointed every iteration: --resume continues an interrupted "
                        "run), never (in memory: the ordered copy and the buffers, the factor "
                        "as --factor-storage auto says; no checkpoint: an interrupted run "
                        "starts again; the adjusted project "
                        "written in one write) or auto (never for a project file up to 64 MB "
                        "and a sixteenth of --memory, a run of seconds; always beyond, with "
                        "--keep-scratch or to --resume a run; the default)")
    a.add_argument("--page-stations", type=int, default=None, metavar="N",
                   help="above N stations keep the per-station vectors (orientations, step, "
                        "variances: 48 bytes a photo each) in memory-mapped scratch files "
                        "beside the project, their pages returned to the page cache as the "
                        "passes move on (default 2000000; 0: always)")
    a.add_argument("--precision", choices=("full", "stations", "none"), default="full",
                   help="the precision pass after convergence: full (the default: photos' and "
                        "points' standard deviations, redundancy numbers and tests of the "
                        "observations), stations (the photos' alone, in a fraction of the "
                        "time) or none")
    a.add_argument("--reset-rejections", action="store_true",
                   help="bring back the observations an earlier run's data snooping rejected "
                        "(default: they stay out, and the report says how many)")
    a.add_argument("--snooping-batch", action="store_true",
                   help="data snooping in batches (implies --snooping): it rejects in one "
                        "round every significant test whose "
                        "photos no other rejection of the round shares, then confirms the "
                        "rejections (each tested as if brought back alone, its residual "
                        "predicted from the others; one no longer significant comes back); "
                        "far fewer rounds on large blocks than the default, the largest test "
                        "alone each round")
    a.add_argument("--alpha", type=float, default=0.001,
                   help="significance level of data snooping (default 0.001: |w| > 3.29)")
    a.add_argument("--method", choices=("auto", "gauss-newton", "levenberg-marquardt"),
                   default="auto",
                   help="auto (default): Gauss-Newton, turning into Levenberg-Marquardt at the "
                        "first step that raises the cost (always for a free network)")
    a.add_argument("--tol-cost", type=float, default=1e-6,
                   help="Levenberg-Marquardt: converged when a step lowers the cost by less "
                        "than this fraction (default 1e-6, Ceres' function tolerance)")
    a.add_argument("--calibrate", default=None, metavar="PARAMS",
                   help="self-calibration: adjust these parameters of every camera (shared "
                        "by its photos) with the block, e.g. f,x0,y0,k1,k2 (any of f, x0, y0, "
                        "k1, k2, k3, p1, p2, b1, b2; of either distortion model; ap: the "
                        "coefficients of the camera's additional-parameter set, Ebner's or "
                        "Gruen's, or some of them a1 .. a44; default: none, the cameras held)")
    a.add_argument("--calibrate-cameras", default=None, metavar="IDS",
                   help="with --calibrate: only these camera ids, e.g. 1,3 (default: every "
                        "camera)")
    a.add_argument("--datum", action="append", default=[],
                   metavar="control|priors|free|fix:IDS:PARAMS",
                   help="the datum (repeatable for fix): control (the control points alone, "
                        "station priors not used), priors (the station priors alone, control "
                        "points used as check points), free (neither: a free network by inner "
                        "constraints on the object points, control points as check points), "
                        "or hold station parameters fixed as true constraints, "
                        "fix:101:all fix:102:X,Y,Z fix:103,104:Z (X, Y, Z, and omega, phi, "
                        "kappa only together), their photos defining the datum with whatever "
                        "else there is, e.g. 7 parameters for a block without control "
                        "(default: the project's control and priors, or a free network when "
                        "it has neither)")
    a.add_argument("--calibrate-per-photo", default=None, metavar="PARAMS",
                   help="self-calibration: adjust these camera parameters per photo (each "
                        "photo of a calibrated camera its own value), e.g. x0,y0 with "
                        "--calibrate f,k1,k2 shared by the camera's photos; default none)")
    a.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its last completed iteration "
                        "(default: start from the project's values)")
    a.add_argument("--memory", default=None, metavar="SIZE",
                   help="memory budget, e.g. 2G: of the external sorts when the project is "
                        "ordered first (default 512M); on the partition tree, of the whole "
                        "adjustment (default 1G; larger fronts are tiled); on the band, a "
                        "quarter of it (of 1G by default) for factor rows kept in core")
    a.add_argument("--keep-scratch", action="store_true",
                   help="keep the work directory NAME.h5.work (band and factor rows; "
                        "default: removed after the run)")
    a.add_argument("--no-progress", action="store_true",
                   help="no progress bars (default: progress bars when standard error is a "
                        "terminal)")
    a.add_argument("--quiet", action="store_true",
                   help="do not print the report (default: print it)")
    _output_options(a)
    a.set_defaults(func=cmd_adjust)

    r = sub.add_parser("report", help="the report of an adjusted project, its CSV tables and "
                                      "plots",
                       description="Print the report that sapgo adjust stored with the "
                                   "solution, and write its CSV tables (--csv) and plots "
                                   "(--plots).")
    r.add_argument("project", help="the project file (e.g. block.h5)")
    r.add_argument("--json", action="store_true",
                   help="print the report as JSON (default: as text)")
    r.add_argument("--quiet", action="store_true",
                   help="do not print the report (default: print it)")
    _output_options(r)
    r.set_defaults(func=cmd_report)

    e = sub.add_parser("export", help="write a project as text files (inputs, or with "
                                      "--adjusted the adjusted photos and points), or as "
                                      "BAL, Bundler, COLMAP, OpenSfM or PhotoModeler",
                       description="Write a project's inputs (or with --adjusted its adjusted "
                                   "photos and points) as text files that sapgo import "
                                   "reads, or in another program's format.")
    e.add_argument("project", help="the project file (e.g. block.h5)")
    e.add_argument("directory", help="output directory (created); with --format bal or "
                                     "bundler the file")
    e.add_argument("--format", choices=("text", "bal", "bundler", "colmap", "opensfm",
                                        "photomodeler"),
                   default="text",
                   help="text files (default), one BAL problem file, one Bundler v0.3 "
                        "bundle.out, an OpenSfM dataset (a project imported from one) or a "
                        "COLMAP text model "
                        "(cameras.txt, images.txt, points3D.txt in the directory)")
    e.add_argument("--adjusted", action="store_true",
                   help="adjusted_photos.txt and adjusted_points.txt in the user's CRS (with "
                        "--format bal, bundler or colmap: the adjusted values in that "
                        "format; default: the inputs)")
    e.add_argument("--pixel-size", type=float, metavar="UM",
                   help="with --format colmap or photomodeler: the pixel size in "
                        "micrometres, to write a project whose image coordinates are in mm "
                        "in pixels (default: none; needed for such a project)")
    e.add_argument("--angles", choices=("deg", "gon", "rad"), default="deg",
                   help="unit of the photos' angles (default deg)")
    e.add_argument("--rotation", choices=("opk", "pok", "kpo"), default="opk",
                   help="the order of the photos' three angles (as sapgo import --rotation; "
                        "default opk)")
    e.add_argument("--orientation", choices=("tangent", "geocentric"), default="tangent",
                   help="with --adjusted and a CRS: angles to the east-north-up frame at each "
                        "photo (default) or to the body-fixed axes")
    e.set_defaults(func=cmd_export)

    pl = sub.add_parser(
        "plan", help="predict the reduced matrix's pattern, band width, fill-in, storage and "
                     "solve time of a flight design or a project, for each ordering",
        description="Predict, for each ordering, the reduced normal matrix's pattern, band "
                    "width, fill-in, storage and solve time, of a flight design (--strips, "
                    "--photos-per-strip, ...) or of an existing project; the ordering of "
                    "the least work is recommended.")
    pl.add_argument("project", nargs="?",
                    help="an existing project (its actual network; default: none, give a "
                         "flight design)")
    pl.add_argument("--strips", type=int, metavar="N",
                    help="flight design: number of strips (no default: needed without a "
                         "project)")
    pl.add_argument("--photos-per-strip", type=int, metavar="N",
                    help="flight design: photos per strip (no default: needed without a "
                         "project)")
    pl.add_argument("--forelap", default="60", help="forelap, %% or fraction (default 60)")
    pl.add_argument("--sidelap", default="20", help="sidelap, %% or fraction (default 20)")
    pl.add_argument("--units", choices=("photos", "models"), default="photos",
                    help="photos (bundle, 6 parameters; the default) or independent models "
                         "(7)")
    pl.add_argument("--cross", action="store_true",
                    help="with --units models: cross models between the strips (+C; a "
                         "sidelap of 50 %% or more; default: none)")
    pl.add_argument("--model-step", type=int, default=None,
                    help="models from photos this many apart (default 1; 2 from 75 %% "
                         "forelap on, as Rostom assumes for 80 %%)")
    _design_arguments(pl)
    pl.add_argument("--json", metavar="PATH",
                    help="write the counts as JSON to PATH (default: none)")
    pl.add_argument("--plot", metavar="PNG",
                    help="draw the pattern of M with its fill-in into PNG (needs matplotlib; "
                         "default: none)")
    pl.add_argument("--plot-ordering", choices=("down_strip", "across_strip", "diagonal",
                                                "rcm", "spiral", "adjust"),
                    help="the ordering drawn (default: the recommended one; adjust: the "
                         "order 'sapgo order' gives a project)")
    pl.add_argument("--no-timing", action="store_true",
                    help="do not measure this machine's solver rate (no predicted times; "
                         "default: measured)")
    pl.set_defaults(func=cmd_plan)

    i = sub.add_parser("info", help="describe a project file",
                       description="Describe a project file: its counts of cameras, photos, "
                                   "points and observations, its frame, whether and how it "
                                   "is ordered, and whether it holds an adjusted solution.")
    i.add_argument("project", help="the project file (e.g. block.h5)")
    i.add_argument("--json", action="store_true",
                   help="print it as JSON (default: one item a line)")
    i.set_defaults(func=cmd_info)
    return ap


#: The first run's compilation of the kernels, measured on a cold cache on 2 cores: the
#: README's demo command (generate and adjust of SAPGO-P-3 on the band) 38 s, a tree run
#: 30 s, then the band's kernels 20 s more (README).
FIRST_RUN_SECONDS = "30-50"


def _quiet_hdf5_teardown(unraisable):
    """After a full disk, HDF5's objects fail again when Python collects them; their
    tracebacks say nothing the one-line error has not said."""
    if isinstance(unraisable.exc_value, RuntimeError) and "ref count" in str(
            unraisable.exc_value):
        return
    sys.__unraisablehook__(unraisable)


def _os_message(exc):
    """One line for an ``OSError``: the file and the system's words, or the first line of
    HDF5's message without its error-stack details."""
    where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
    text = exc.strerror or str(exc)
    text = text.splitlines()[0] if text else type(exc).__name__
    if "(" in text and "Unable to" in text:   # h5py: "Unable to ... (detail)"
        text = text.split("(")[0].strip() + " (" + text.split("(", 1)[1].split(",")[0]
        text = text.rstrip(")") + ")"
    return f"{where}{text}"


def main(argv=None):
    from .errors import DiskFullError
    from .project import disk_full_error, is_disk_full

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and getattr(args, "command", None) == "import" and not any(
            e.startswith("-") for e in extra):   # (import's paths around its options)
        args.paths += extra
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    sys.unraisablehook = _quiet_hdf5_teardown
    from . import kernelcache

    if kernelcache.FIRST_RUN and args.func not in (cmd_info,):
        print(f"sapgo: compiling the numerical kernels for this installation, once (about "
              f"{FIRST_RUN_SECONDS} s; kept in {kernelcache.CACHE_DIR})", file=sys.stderr)
        kernelcache.FIRST_RUN = False
    try:
        try:
            return args.func(args)
        except (OSError, RuntimeError) as exc:   # (HDF5's words for a full disk: ours)
            if not is_disk_full(exc):
                raise
            raise disk_full_error(getattr(args, "project", "") or "the output", exc) from None
    except DiskFullError as exc:
        print(f"sapgo: error: {exc}", file=sys.stderr)
        if argv is None:   # (the command line: no teardown of HDF5 on a full disk)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(2)
        return 2
    except SapgoError as exc:
        print(f"sapgo: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"sapgo: error: {_os_message(exc)}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"sapgo: error: {args.command}: out of memory (a --memory larger than this "
              f"machine can give? the default fits any block)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sapgo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
