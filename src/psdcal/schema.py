"""JSON Schema (draft 2020-12) of the calibration file that ``psdcal calibrate`` writes.

:func:`calibration_schema` describes every key of
:meth:`psdcal.calibration.core.CalibrationResult.to_dict` with its type,
range and unit; the keys of the file contract are required.  Keys beyond
those described are allowed everywhere but in ``intrinsics`` and
``distortion`` (the contract lets later versions add keys that keep their
meaning), so an older validator accepts a newer file; the tests check that
every key the tool writes is described.  ``psdcal export --format json-schema`` writes it.
"""
from __future__ import annotations

SCHEMA_ID = "https://psdcal.invalid/schema/calibration.json"

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_ID = {"type": ["integer", "string"]}
_VEC3 = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
_NUMS = {"type": "array", "items": _NUM}
_DIST_NAMES = ("k1", "k2", "k3", "p1", "p2", "l1", "l2")
_DIST_UNITS = {"k1": "mm^-2", "k2": "mm^-4", "k3": "mm^-6", "p1": "mm^-1", "p2": "mm^-1", "l1": "mm^-2",
               "l2": "mm^-4"}


def _obj(props: dict, required=(), *, extra: bool = True, description: str = "") -> dict:
    out = {"type": "object", "properties": props, "required": list(required), "additionalProperties": extra}
    if description:
        out["description"] = description
    return out


def calibration_schema() -> dict:
    """The JSON Schema (draft 2020-12) of a psdcal calibration file, as a dict.

    Returns
    -------
    dict
        Serialise it with ``json.dumps``; validate a file with e.g.
        ``jsonschema.Draft202012Validator(calibration_schema()).validate(d)``.
    """
    _prior = _obj(
        {"names": {"type": "array", "items": {"type": "string"}}, "mean": _NUMS,
         "covariance": {"type": "array", "items": {"type": "array", "items": _NUM_OR_NULL}},
         "source": {"type": "string"}},
        ("names", "mean", "covariance"),
        description="a Gaussian prior (--prior): mean and covariance of the named parameters (null: infinite)",
    )
    intrinsics = _obj(
        {
            "f_mm": {"type": "number", "exclusiveMinimum": 0, "description": "focal length, mm"},
            "cx_mm": {"type": "number", "description": "optical centre x from the PSD's electrical centre, mm"},
            "cy_mm": {"type": "number", "description": "optical centre y, mm"},
            "skew": {"type": "number", "description": "skew (the paper's gamma), mm; 0 when not estimated"},
            "fy_mm": {"type": "number", "exclusiveMinimum": 0,
                      "description": "separate vertical focal length, mm (only with model.aspect)"},
        },
        ("f_mm", "cx_mm", "cy_mm", "skew"),
        extra=False,
        description="pinhole intrinsics (Eq 4, 21), mm on the sensor",
    )
    distortion = _obj(
        {n: {"type": "number", "description": f"undistortion coefficient, {_DIST_UNITS[n]}; 0 when not in the model"}
         for n in _DIST_NAMES},
        _DIST_NAMES,
        extra=False,
        description="undistortion coefficients (Eq 7-16): lens k1..k3, p1, p2 about the optical centre, PSD l1, l2",
    )
    std = _obj(
        {n: {"type": ["number", "null"], "minimum": 0} for n in ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm",
                                                                   *_DIST_NAMES, "g_x2", "g_y1", "g_y2")},
        ("f_mm", "cx_mm", "cy_mm", "skew", *_DIST_NAMES),
        description="standard errors in the parameters' units; null where the parameter is fixed",
    )
    extrinsic = _obj(
        {
            "image_id": _ID,
            "rvec": {**_VEC3, "description": "rotation vector (Rodrigues), rad: template to sensor frame"},
            "tvec_mm": {**_VEC3, "description": "translation, mm: Pc = R P + t"},
            "std": {"type": "array", "items": _NUM_OR_NULL, "minItems": 6, "maxItems": 6,
                    "description": "standard errors of rvec (rad) and tvec_mm (mm)"},
        },
        ("image_id", "rvec", "tvec_mm"),
    )
    residuals = _obj(
        {
            "rms_mm": {"type": ["number", "null"], "minimum": 0,
                       "description": "RMS distance on the sensor between measured and modelled points, mm"},
            "per_image_rms_mm": {"type": "array", "items": {"type": ["number", "null"], "minimum": 0}},
            "cost_rms": {"type": ["number", "null"], "minimum": 0,
                         "description": "RMS residual of the minimised cost in its own unit (mm)"},
            "sigma_mm": {"type": ["number", "null"], "minimum": 0,
                         "description": "noise standard deviation per coordinate implied by the fit, mm"},
            "points": _obj(
                {
                    "columns": {"const": ["image_id", "point_id", "dx_mm", "dy_mm"]},
                    "rows": {"type": "array", "items": {"type": "array", "prefixItems": [_ID, _ID, _NUM, _NUM],
                                                       "minItems": 4, "maxItems": 4}},
                },
                ("columns", "rows"),
                description="residual (measured minus modelled) of every observed point, mm on the sensor",
            ),
        },
        ("rms_mm", "per_image_rms_mm"),
    )
    switches = {  # the model switches, in `model` and in the problem record's `options`
        "radial": {"type": "integer", "minimum": 0, "maximum": 3},
        "tangential": {"type": "boolean"},
        "psd_radial": {"type": "integer", "minimum": 0, "maximum": 2},
        "skew": {"type": "boolean"},
        "aspect": {"type": "boolean"},
        "fit_gains": {"type": "boolean"},
    }
    model = _obj(
        dict(switches),
        ("radial", "tangential", "psd_radial", "skew"),
        description="the model switches: which parameters were estimated",
    )
    options = _obj(
        {
            "cost": {"enum": ["image", "template"]},
            **switches,
            "preliminary": {"type": "boolean"},
            "normalize": {"type": "boolean"},
            "gains": {"type": ["array", "null"], "items": {"type": "number", "exclusiveMinimum": 0}, "minItems": 4,
                      "maxItems": 4, "description": "known relative channel gains (null: not given)"},
            "fix": {"type": "object", "additionalProperties": _NUM,
                    "description": "parameters held at a value (--fix NAME=VALUE), name -> value"},
            "priors": {"type": "array", "items": _prior},
            "fix_gains_applied": {"type": "object", "additionalProperties": _NUM},
            "f_guess_mm": {"type": ["number", "null"], "exclusiveMinimum": 0,
                           "description": "nominal focal length given with --f-guess, mm"},
            "distance_mm": {"type": ["number", "null"], "exclusiveMinimum": 0,
                            "description": "direction calibration: source distance from the stage axes, mm"},
            "sensor_mm": {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0}, "minItems": 2,
                          "maxItems": 2},
            "solver": _obj({"ftol": _NUM, "xtol": _NUM, "gtol": _NUM,
                            "max_iterations": {"type": "integer", "minimum": 1}}, extra=True),
        },
        ("radial", "tangential", "psd_radial", "skew"),
        extra=True,
    )
    xy = {"type": "array", "items": {"type": "array", "items": _NUM, "minItems": 2, "maxItems": 2}}
    xy_or_null = {"type": "array", "items": {"type": "array", "items": {
        "type": "array", "items": _NUM_OR_NULL, "minItems": 2, "maxItems": 2}}}
    problem = _obj(
        {
            "kind": {"enum": ["directions"], "description": "absent for template views; 'directions': a stage sweep"},
            "directions": _obj({"az_deg": _NUMS, "el_deg": _NUMS, "point_ids": {"type": "array", "items": _ID}},
                               ("az_deg", "el_deg")),
            "stage": {"type": "object", "description": "direction calibration: the stage fit (rotation, offsets)"},
            "fit": {"type": "object", "description": "direction calibration: the full state, its covariance, sigma2"},
            "prior_fit": _obj({"sigma2": _NUM, "dof": _NUM, "prior_dof": _NUM,
                               "rounds": {"type": "integer", "minimum": 0}},
                              description="the refit with --fix/--prior: noise variance and degrees of freedom"),
            "template": _obj({"point_ids": {"type": "array", "items": _ID}, "xy_mm": xy}, ("point_ids", "xy_mm")),
            "points": _obj({"image_ids": {"type": "array", "items": _ID}, "xy_mm": xy_or_null}, ("image_ids", "xy_mm"),
                           extra=True),
            "options": options,
            "outlier_rejection": _obj(
                {
                    "k": {"type": "number", "exclusiveMinimum": 0, "description": "threshold, robust sigmas"},
                    "sigma_mm": {"type": ["number", "null"], "minimum": 0, "description": "robust noise sigma, mm"},
                    "rounds": {"type": "integer", "minimum": 0},
                    "removed": {"type": "array", "items": _obj(
                        {"image_id": _ID, "point_id": _ID, "x_mm": _NUM, "y_mm": _NUM, "dx_mm": _NUM, "dy_mm": _NUM,
                         "ratio": _NUM, "round": {"type": "integer", "minimum": 1},
                         "line": {"type": ["integer", "null"], "minimum": 1},
                         "residual_mm": {"type": "number", "minimum": 0}},
                        ("image_id", "point_id", "x_mm", "y_mm", "dx_mm", "dy_mm"))},
                    "kept_flagged": {"type": "array", "items": {"type": "array", "prefixItems": [_ID, _ID],
                                                                "minItems": 2, "maxItems": 2}},
                },
                ("k", "removed"),
                description="points removed by `calibrate --reject K` (psdcal.calibration.outliers)",
            ),
            "files": {"type": "object", "additionalProperties": _obj(
                {"path": {"type": "string"}, "sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"}},
                ("path", "sha256"))},
        },
        ("points", "options"),
        extra=True,
        description="the inputs and options: enough to re-run the calibration exactly (psdcal.recalibrate)",
    )
    stages = _obj(
        {
            "preliminary": _obj({"k1": _NUM, "k2": _NUM, "line_groups": {"type": "integer", "minimum": 0},
                                 "applied": {"type": "boolean"}}, extra=True),
            "closed_form": _obj(
                {"f_mm": _NUM, "cx_mm": _NUM, "cy_mm": _NUM, "skew": _NUM, "fy_mm": _NUM_OR_NULL,
                 "normalized": {"type": "boolean", "description": "Hartley normalisation of the DLT"},
                 "points_per_view": {"type": "integer", "minimum": 1,
                                     "description": "the homographies were fitted to this many spread points per "
                                                    "view (about; the final fit takes every point)"}},
                extra=True, description="the closed-form intrinsics (the paper's Tables 1-2) and `normalized`"),
            "initial_extrinsics": {"type": "array", "items": _obj(
                {"image_id": _ID, "rvec": _VEC3, "tvec_mm": _VEC3}, ("image_id", "rvec", "tvec_mm"))},
            "multistart": _obj(
                {"starts": {"type": "array", "items": _obj(
                    {"start": {"type": "string"}, "cost_rms": _NUM_OR_NULL, "converged": {"type": "boolean"},
                     "f_mm": _NUM_OR_NULL, "cx_mm": _NUM_OR_NULL, "cy_mm": _NUM_OR_NULL}, ("start", "converged"))},
                 "chosen": {"type": "string"},
                 "points_per_view": {"type": "integer", "minimum": 1,
                                     "description": "the starts were compared on this many spread points per view"}},
                ("starts", "chosen"),
                description="the refinement's starts and the lowest-cost one chosen",
            ),
            "linear": {"type": "object", "description": "direction calibration: the linear start"},
            "covariance_inflation": _obj(
                {"factor": {"type": "number", "minimum": 1},
                 "checks": {"type": "array", "items": {"type": "string"}},
                 "rule": {"type": "string"}},
                ("factor",),
                description="the factor the verdict multiplied the covariance by (1 + effect_sigma^2 of its largest "
                            "effect; absent when 1) and the checks that asked for it"),
        },
        extra=True,
        description="starting values each linear step produced (the paper's Tables 1-2)",
    )
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": SCHEMA_ID,
        "title": "psdcal calibration",
        "description": "A PSD + lens sensor calibration written by `psdcal calibrate` (lengths in mm, angles in rad). "
                       "More top-level keys may be added by later versions; the listed ones keep their meaning.",
        "type": "object",
        "properties": {
            "intrinsics": intrinsics,
            "distortion": distortion,
            "std": std,
            "extrinsics": {"type": "array", "items": extrinsic, "description": "one pose per template view"},
            "residuals": residuals,
            "cost": {"enum": ["image", "template"], "description": "the minimised cost"},
            "iterations": {"type": "integer", "minimum": 0},
            "converged": {"type": "boolean"},
            "message": {"type": "string", "description": "the solver's stopping reason"},
            "model": model,
            "gains": {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0}, "minItems": 4,
                      "maxItems": 4, "description": "relative channel gains (g_x1, g_x2, g_y1, g_y2), g_x1 = 1"},
            "covariance": _obj(
                {"names": {"type": "array", "items": {"enum": ["f_mm", "cx_mm", "cy_mm", "skew", "fy_mm", *_DIST_NAMES,
                                                                "g_x2", "g_y1", "g_y2"]}, "uniqueItems": True},
                 "matrix": {"type": "array", "items": {"type": "array", "items": _NUM_OR_NULL}}},
                ("names", "matrix"),
                description="covariance of the free global parameters (poses marginalised), in their units squared",
            ),
            "sensor": _obj({"lx_mm": {"type": "number", "exclusiveMinimum": 0},
                            "ly_mm": {"type": "number", "exclusiveMinimum": 0}}, ("lx_mm", "ly_mm"),
                           description="PSD active lengths, mm"),
            "stages": stages,
            "problem": problem,
            "software": _obj({"name": {"const": "psdcal"}, "version": {"type": "string"}}, ("name", "version"),
                             extra=True),
            "created": {"type": "string", "description": "UTC time of the calibration, ISO 8601"},
            "warnings": {"type": "array", "items": {"type": "string"},
                         "description": "what looks wrong although the solver converged"},
            "verdict": {"enum": ["good", "suspect", "wrong"],
                        "description": "the statistical self-check of the fit (psdcal.calibration.verdict)"},
            "checks": {"type": "array", "items": _obj(
                {"name": {"type": "string"}, "statistic": _NUM_OR_NULL, "threshold": _NUM_OR_NULL,
                 "p_value": {"type": ["number", "null"], "minimum": 0, "maximum": 1},
                 "false_alarm": {"type": "number", "minimum": 0, "maximum": 1},
                 "passed": {"type": ["boolean", "null"], "description": "null: not applicable"},
                 "message": {"type": "string"}, "advice": {"type": "string"}, "severe": {"type": "boolean"},
                 "dof": {**_NUM_OR_NULL, "description": "degrees of freedom of the statistic"},
                 "effect_sigma": {**_NUM_OR_NULL, "description": "how far the problem moves f, C or the angles over "
                                                                 "the field of view, in their standard errors"},
                 "inflation": {**_NUM_OR_NULL, "description": "the factor this check asks of the covariance "
                                                              "(1 + effect_sigma^2; 1: none)"}},
                ("name", "passed", "message"))},
        },
        "required": ["intrinsics", "distortion", "std", "extrinsics", "residuals", "cost", "iterations", "converged",
                     "model", "software"],
        "additionalProperties": True,
    }


__all__ = ["SCHEMA_ID", "calibration_schema"]
