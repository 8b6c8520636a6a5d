"""`psdcal calibrate`: points + template -> calibration JSON."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli


def model_options(f):
    """The model switches shared by calibrate-like commands."""
    opts = [
        click.option("--cost", type=click.Choice(["image", "template"]), default="image", show_default=True,
                     help="image: maximum-likelihood residual on the sensor; template: the paper's Eq 29 on the plate."),
        click.option("--radial", type=click.IntRange(0, 3), default=2, show_default=True, help="Lens radial terms k1..k3."),
        click.option("--tangential/--no-tangential", default=True, show_default=True, help="Lens tangential terms p1, p2."),
        click.option("--psd-radial", type=click.IntRange(0, 2), default=0, show_default=True, help="PSD radial terms l1, l2."),
        click.option("--skew/--no-skew", default=False, show_default=True, help="Estimate the skew."),
        click.option("--aspect/--no-aspect", default=False, show_default=True, help="Separate vertical focal length fy_mm."),
        click.option("--preliminary/--no-preliminary", default=True, show_default=True,
                     help="Line-straightness preliminary distortion estimate (Section 3.2)."),
        click.option("--normalize/--no-normalize", default=True, show_default=True,
                     help="Hartley normalisation of the DLT (Section 3.3)."),
        click.option("--sensor-mm", type=(float, float), default=(9.0, 9.0), show_default=True,
                     help="PSD active lengths Lx Ly, mm (S5991-01: 9 9)."),
        click.option("--max-iterations", type=click.IntRange(1, 100000), default=200, show_default=True,
                     help="LM iteration limit; more is a convergence failure (exit 2)."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


#: Most template points ``calibrate`` accepts (the line search costs O(M^2 log M)).
MAX_TEMPLATE_POINTS = 2000


@cli.command("calibrate")
@click.argument("points", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--template", "-t", "template", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Template CSV: point_id,X_mm,Y_mm.")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Calibration JSON to write (only written when the calibration succeeds).")
@model_options
@click.option("--fit-gains", is_flag=True, default=False,
              help="Estimate the three relative channel gains jointly (POINTS must carry raw amplitudes vx1,vx2,vy1,vy2).")
@click.option("--reject", "reject_k", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="K",
              help="Remove points whose residual exceeds K robust noise sigmas, refit, and list them (e.g. 5). "
                   "Refused (exit 2, with the diagnosis) when the misfit is systematic rather than a few points.")
@click.option("--fix", "fix_items", multiple=True, metavar="NAME=VALUE",
              help="Hold a global parameter at VALUE (repeatable): f_mm, cx_mm, cy_mm, skew, fy_mm, k1-k3, p1, p2, "
                   "l1, l2, g_x2, g_y1, g_y2. E.g. --fix f_mm=8.0 --fix k2=0. Its std is reported as null.")
@click.option("--prior", "prior_items", multiple=True, metavar="NAME=VALUE,STD",
              help="Gaussian prior VALUE +- STD on a free global parameter (repeatable), e.g. --prior f_mm=8.0,0.05. "
                   "STD 0 fixes it, inf is no prior.")
@click.option("--prior-file", "prior_files", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="JSON prior with a mean vector and covariance (keys names, values|mean|gains, covariance|std), "
                   "e.g. the gains JSON of `psdcal gains` with --fit-gains (repeatable).")
@click.option("--f-guess", "f_guess_mm", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="F_MM",
              help="Nominal focal length, mm (lens data sheet): one more start of the refinement, and the start "
                   "used when the views alone give none.")
@click.option("--noise-um", "noise_um", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="SIGMA_UM",
              help="Known noise standard deviation per coordinate of the points, um (e.g. from the lock-in's "
                   "amplitude noise): the verdict then also tests the residual RMS against it.")
@click.option("--model", "model_choice", type=click.Choice(["manual", "auto"]), default="manual", show_default=True,
              help="auto: choose radial, tangential, PSD radial terms and skew by nested F-tests (forward selection "
                   "from f, C, k1; the switches are then ignored) and print the selection path.")
@click.option("--cross-validate", "cv_k", type=click.IntRange(min=2), default=None, metavar="K",
              help="Refit K times leaving a fold of views out, predict the left-out views' points and test the "
                   "errors against the predicted uncertainty (adds the check 'cross_validation').")
@click.option("--strict", is_flag=True, default=False,
              help="Exit 2 (and write no --output) unless the verdict is good.")
@click.option("--gains", "gains_file", type=click.Path(dir_okay=False),
              help="Gains JSON from 'psdcal gains' (bench): the channel gains, held fixed (the start with "
                   "--fit-gains); kept in the calibration JSON.")
@click.option("--sensor-id", "sensor_id", default=None, metavar="ID",
              help="Identity of the calibrated sensor (serial number, lens): kept as sensor_id in the JSON, shown "
                   "by report, checked by `locate/aoa --expect-sensor ID`.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")
def calibrate_command(points, template, output, cost, radial, tangential, psd_radial, skew, aspect, preliminary,
                      normalize, sensor_mm, max_iterations, fit_gains, quiet, reject_k=None, f_guess_mm=None,
                      noise_um=None, strict=False, model_choice="manual", cv_k=None, fix_items=(),
                      prior_items=(), prior_files=(), gains_file=None, sensor_id=None):
    """Calibrate a PSD + lens sensor from views of a planar LED template.

    POINTS is a CSV of impact points, `image_id,point_id,x_mm,y_mm` (a missing
    point is a missing row), or of raw amplitudes `image_id,point_id,vx1,vx2,vy1,vy2`.
    Prints the parameters with standard errors and the residual RMS, the
    verdict (good / suspect / wrong) with the self-checks that failed and the
    advice that fixes their cause, and writes the calibration JSON (with
    `verdict` and `checks`) to --output.

    Example: psdcal calibrate points.csv -t template.csv -o calib.json --psd-radial 1
    """
    one_thread = _one_blas_thread()
    from psdcal.calibration.core import calibrate, with_verdict
    from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
    from psdcal.io import read_points, read_template, save_calibration
    from psdcal.report.text import print_calibration

    if sensor_id is not None and (not sensor_id.strip() or any(c in sensor_id for c in "\r\n\x00")):
        raise InputError(f"--sensor-id must be a non-empty single line, got {sensor_id!r}", field="--sensor-id")
    fix, priors = None, []
    if fix_items or prior_items or prior_files:
        from psdcal.calibration.priors import parse_fix, parse_prior, read_prior_file

        fix = parse_fix(fix_items) or None
        priors = [parse_prior(t) for t in prior_items] + [read_prior_file(f) for f in prior_files]
    tids, txy = read_template(template)
    if len(tids) > MAX_TEMPLATE_POINTS:
        raise InputError(f"{len(tids)} template points: more than the {MAX_TEMPLATE_POINTS} a calibration handles "
                         "(the line search is quadratic in them); use a subset of the LEDs", path=template)
    pf = read_points(points, tids, sensor_mm=sensor_mm)
    from psdcal._limits import check_bytes

    n_img, n_pts = pf.points_mm.shape[:2]
    check_bytes(2.0 * n_img * n_pts * (20 + 6 * n_img) * 8 * 3, f"{n_img} views of {n_pts} points", "POINTS")
    if fit_gains and pf.kind != "amplitudes":
        raise InputError("--fit-gains needs raw amplitudes (header image_id,point_id,vx1,vx2,vy1,vy2)", path=points, line=1)
    from psdcal.calibration._refine import SolverOptions, assume_one_blas_thread

    if one_thread:
        assume_one_blas_thread()  # no threadpoolctl: the BLAS started with one thread
    _kernels_for(pf.points_mm, quiet)
    bench_gains = None
    if gains_file is not None:
        from psdcal.calibration.bench import load_gains

        bench_gains = load_gains(gains_file)[0]
    noise_mm = None if noise_um is None else noise_um * 1e-3
    common = dict(cost=cost, preliminary=preliminary, normalize=normalize, aspect=aspect, fit_gains=fit_gains,
                  gains=bench_gains,
                  image_ids=pf.image_ids, point_ids=tids, sensor_mm=tuple(sensor_mm),
                  solver=SolverOptions(max_iterations=max_iterations), f_guess_mm=f_guess_mm)
    try:
        if model_choice == "auto" and (fix or priors):
            raise InputError("--model auto cannot be combined with --fix, --prior or --prior-file", field="model")
        if model_choice == "auto":
            from psdcal.calibration.model_select import describe_selection, select_model

            res, steps = select_model(txy, pf.points_mm, **common)
            if not quiet:
                m = res.model
                click.echo(f"--model auto: radial {m.radial}, tangential {'on' if m.tangential else 'off'}, "
                           f"psd-radial {m.psd_radial}, skew {'on' if m.skew else 'off'} (nested F-tests, alpha 1e-3):")
                for line in describe_selection(steps):
                    click.echo(line)
        else:
            res = calibrate(txy, pf.points_mm, radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew,
                            verdict=False, **common, **({"fix": fix, "priors": priors} if (fix or priors) else {}))
    except DegenerateViewsError as exc:
        raise DegenerateViewsError(f"{points}: {exc}") from None
    except ConvergenceError as exc:
        raise ConvergenceError(f"{points}: {exc}{_diagnosis(exc.result, noise_mm, pf.kind)}") from None
    if reject_k is not None:
        from psdcal.calibration.outliers import refuse_if_systematic, reject_outliers

        refuse_if_systematic(res, reject_k, points_kind=pf.kind)
        rej = reject_outliers(res, reject_k, line_numbers=pf.line_numbers)
        res = rej.result
        if not quiet:
            click.echo(f"--reject {reject_k:g}: removed {len(rej.removed)} point(s) above {reject_k:g} x "
                       f"{rej.sigma_mm * 1e3:.3f} um (robust noise sigma), {rej.rounds} refit(s)")
            for p in rej.removed:
                click.echo(f"  {points}:{p.line}: image {p.image_id}, point {p.point_id} at ({p.x_mm:.4f}, {p.y_mm:.4f}) mm, "
                           f"residual {p.residual_mm * 1e3:.2f} um = {p.ratio:.1f} sigma")
            for iid, pid in rej.kept_flagged:
                click.echo(f"  kept (too few points left to remove it): image {iid}, point {pid}")
    from psdcal.errors import DegenerateViewsError

    try:
        undetermined_parameters(res, points)
        undetermined = None
    except DegenerateViewsError as exc:
        undetermined = exc
    res = with_verdict(res, noise_mm=noise_mm, points_kind=pf.kind)
    if undetermined is not None and res.verdict["verdict"] != "wrong":
        # a fit the data contradict (verdict wrong) has a covariance of no meaning: its diagnosis says more
        raise undetermined
    if cv_k is not None:
        import dataclasses

        from psdcal.calibration.model_select import cross_validate
        from psdcal.calibration.verdict import with_check

        cv = cross_validate(res, cv_k)
        res = dataclasses.replace(res, verdict=with_check(res.verdict, cv.check()),
                                  problem={**res.problem, "cross_validation": cv.to_dict()})
        if not quiet:
            click.echo(cv.line())
    res = _with_inputs(res, template, points, gains_file)
    if strict and res.verdict["verdict"] != "good":
        from psdcal.calibration.verdict import Verdict, VerdictError

        if not quiet:
            print_calibration(res)
        v = Verdict.from_dict(res.verdict)
        raise VerdictError(f"--strict: the verdict is {v.verdict} ({'; '.join(v.reasons)}); nothing written")
    if output is not None:
        if sensor_id is not None:
            from psdcal.io import write_json

            write_json(output, {**res.to_dict(), "sensor_id": sensor_id})
        else:
            save_calibration(output, res)
    if not quiet:
        if sensor_id is not None:
            click.echo(f"sensor: {sensor_id}")
        print_calibration(res)
        _echo_constraints(res)
        if output is not None:
            click.echo(f"wrote {output}")


def undetermined_parameters(res, points) -> None:
    """DegenerateViewsError when the covariance shows parameters the views do not determine.

    A negative or non-finite variance, or a covariance that is not positive
    semi-definite, means the normal equations are singular (e.g. every view
    parallel to the sensor: f and the distance trade off exactly). Writing
    such a result would give a standard error of 0 -- a perfect-looking
    calibration of a parameter the data do not fix.
    """
    import numpy as np

    from psdcal.errors import DegenerateViewsError

    C = np.asarray(res.covariance, dtype=float)
    names = list(res.param_names)
    if C.size == 0:
        return
    diag = np.diag(C)
    bad = [n for n, v in zip(names, diag) if not (np.isfinite(v) and v >= 0)]
    if not bad and np.all(np.isfinite(C)):
        d = np.sqrt(diag)
        ok = d > 0
        if ok.sum() >= 2:
            R = C[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
            w, v = np.linalg.eigh(0.5 * (R + R.T))
            if w.min() < -1e-6:
                k = np.argsort(-np.abs(v[:, 0]))[:2]
                sub = [n for n, o in zip(names, ok) if o]
                bad = [sub[i] for i in k]
    if not bad:
        from psdcal.calibration.checks import undetermined_parameters as undetermined

        bad = undetermined(res)  # the same from the reduced information: robust to what round-off made of C
    if bad:
        raise DegenerateViewsError(
            f"{points}: the views do not determine {', '.join(bad)} (their covariance is not a covariance: the "
            "normal equations are singular, e.g. every view parallel to the sensor); tilt the template by "
            "10-40 deg in different directions between views, or fix the parameter with --fix")


def _diagnosis(result, noise_mm, points_kind) -> str:
    """'; verdict: ...' with the first advice of the verdict on an unconverged result ('' when none)."""
    if result is None:
        return ""
    try:
        from psdcal.calibration.verdict import assess

        v = assess(result, noise_mm=noise_mm, points_kind=points_kind)
    except Exception:  # noqa: BLE001 -- the diagnosis of a failed fit is best effort; the error stands without it
        return ""
    tips = [c.advice for c in v.failed if c.advice]
    return f"; diagnosis: {tips[0]}" if tips else ""


def _kernels_for(points_mm, quiet: bool) -> None:
    """One-shot run: the compiled kernels only where they pay for their loading (psdcal._jit, "auto").

    When they are needed and not yet compiled on this machine, say so on one line
    (compiling takes some seconds, once) instead of stalling silently.
    """
    import numpy as np

    from psdcal import _jit

    _jit.set_mode("auto")
    n_obs = int(np.all(np.isfinite(points_mm), axis=-1).sum())
    if _jit.use_compiled(n_obs) and not _jit.cache_is_warm() and not quiet:
        click.echo("psdcal: compiling the numerical kernels (first use on this machine, some seconds; "
                   "`python3 tasks.py` set-up does it ahead) ...", err=True)


def _with_inputs(res, template, points, gains_file=None):
    """Record the input files and their checksums in the result's problem record."""
    import dataclasses

    files = {}
    roles = (("template", template), ("points", points)) + ((("gains", gains_file),) if gains_file else ())
    for role, p in roles:
        files[role] = {"path": str(p), "sha256": _sha256(Path(p).read_bytes()).hexdigest()}
    return dataclasses.replace(res, problem={**res.problem, "files": files})


def _sha256(data: bytes):
    """SHA-256 of ``data`` (a hashlib object): the interpreter's built-in one where it has it, which loads in a
    tenth of the time of hashlib's OpenSSL (the same digest, FIPS 180-4)."""
    for name in ("_sha2", "_sha256"):  # Python >= 3.12, <= 3.11
        try:
            mod = __import__(name)
        except ImportError:
            continue
        if hasattr(mod, "sha256"):
            return mod.sha256(data)
    import hashlib

    return hashlib.sha256(data)


#: BLAS libraries' thread-count variables set to 1 for a ``psdcal calibrate`` process (unless set by the user).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _one_blas_thread() -> bool:
    """Start the BLAS with one thread when numpy is not loaded yet (a fresh ``psdcal calibrate``).

    The calibration and its verdict run on one BLAS thread anyway (small dense
    problems; :func:`psdcal.calibration._refine._single_threaded_blas`), but
    OpenBLAS starts a thread per core when it loads, and those threads spin
    waiting for work: some 40 ms of CPU in a short command on two cores. A
    value the user set is kept; in a process that already has numpy (a test,
    a notebook) nothing changes.

    Returns True when numpy will start its BLAS with one thread (every one of
    these variables is 1 before numpy's first import), so that the calibration
    need not ask threadpoolctl for the limit again.
    """
    import os
    import sys

    if "numpy" in sys.modules:
        return False
    for var in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(var, "1")
    return all(os.environ[var].strip() == "1" for var in BLAS_THREAD_VARIABLES)


def _echo_constraints(res):
    """One line each for the fixed parameters and the priors of a constrained calibration (none otherwise)."""
    o = res.problem.get("options", {}) if res.problem else {}
    if o.get("fix"):
        click.echo("fixed: " + ", ".join(f"{n} = {v:.6g}" for n, v in o["fix"].items()))
    for p in o.get("priors") or []:
        sd = [c[i] ** 0.5 if c[i] is not None else float("inf") for i, c in enumerate(p["covariance"])]
        click.echo(f"prior ({p.get('source') or 'argument'}): " + ", ".join(
            f"{n} = {m:.6g} +- {s:.2g}" for n, m, s in zip(p["names"], p["mean"], sd)))
    pf = res.problem.get("prior_fit") if res.problem else None
    if pf:
        click.echo(f"degrees of freedom {pf['dof']:.2f} (the priors determine {pf['prior_dof']:.2f} parameters); "
                   "noise estimated from the data residuals only")
