"""psdcal export: OpenCV / ROS camera models fitted to psdcal's, and the calibration file's JSON Schema."""
from __future__ import annotations

import json

import numpy as np
import pytest

from psdcal import calibrate
from psdcal.calibration.core import CalibrationResult
from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.measure.aoa import angles_from_points
from psdcal.measure.sensor_model import SensorModel
from psdcal.report.compare import sensor_grid_mm
from psdcal.report.export import fit_opencv, opencv_distort, opencv_undistort, sensor_to_pixels
from psdcal.schema import calibration_schema
from psdcal.study.simulate import LENSES, PAPER_L1, simulate_set

cv2 = pytest.importorskip("cv2")
jsonschema = pytest.importorskip("jsonschema")
yaml = pytest.importorskip("yaml")

CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


@pytest.fixture(scope="module")
def calibs():
    """Calibrations of both lenses (and the PSD term) from simulated views."""
    out = {}
    for lens, psd in (("lens1", 0), ("lens1", 1), ("lens2", 0)):
        s = simulate_set(lens, n_images=10, noise_mm=0.002, seed=3, psd_l1=PAPER_L1 if psd else 0.0)
        out[(lens, psd)] = calibrate(s.template_mm, s.points_mm, psd_radial=psd)
    return out


def _ray_angle_deg(n1, n2):
    r1 = np.concatenate([n1, np.ones(n1.shape[:-1] + (1,))], axis=-1)
    r2 = np.concatenate([n2, np.ones(n2.shape[:-1] + (1,))], axis=-1)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(r1, r2), axis=-1), np.sum(r1 * r2, axis=-1)))


@pytest.mark.parametrize("key,n_coeffs,refine_k", [(("lens1", 0), 5, True), (("lens1", 0), 4, False),
                                                    (("lens1", 1), 5, True), (("lens2", 0), 8, True)])
@pytest.mark.parametrize("pixel_um", [1.0, 1000.0])
def test_cv2_undistort_points_agrees_within_stated_fit_error(calibs, key, n_coeffs, refine_k, pixel_um):
    """OpenCV's own undistortPoints with the exported K, D gives psdcal's rays within the stated error."""
    res = calibs[key]
    m = fit_opencv(res, pixel_um=pixel_um, n_coeffs=n_coeffs, refine_k=refine_k)
    # an independent grid (not the fit's): 37 x 37 with a different spacing
    d = sensor_grid_mm(res.sensor_mm, 37).reshape(-1, 2)
    n_psdcal = angles_from_points(d, SensorModel(intrinsics=res.intrinsics, distortion=res.distortion)).n
    px = sensor_to_pixels(d, res.sensor_mm, pixel_um).reshape(-1, 1, 2)
    n_cv = cv2.undistortPoints(px, m.camera_matrix, m.dist_coeffs, None, None, None, CRITERIA).reshape(-1, 2)
    ang = _ray_angle_deg(n_cv, n_psdcal)
    assert ang.max() <= m.fit_max_deg * 1.05 + 1e-9
    # and the stated error is not a loose bound: the grid's worst point comes close to it
    assert ang.max() >= 0.5 * m.fit_max_deg
    assert m.fit_rms_deg <= m.fit_max_deg
    # the forward direction: cv2.projectPoints of psdcal's rays lands within the stated misfit of d
    rays = np.concatenate([n_psdcal, np.ones((len(d), 1))], axis=1)
    uv = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), m.camera_matrix, m.dist_coeffs)[0].reshape(-1, 2)
    err_um = np.linalg.norm(uv - px.reshape(-1, 2), axis=1) * pixel_um
    assert err_um.max() <= m.fit_max_um * 1.05 + 1e-6


def test_exact_when_psdcal_model_is_an_opencv_model():
    """A calibration whose only distortion is 'undistort' = OpenCV's inverse of pure k1... is not exact;
    but with no distortion at all the fit is exact and K is psdcal's intrinsics in pixels."""
    from dataclasses import replace

    s = simulate_set("lens1", n_images=6, noise_mm=0.0, seed=0)
    res = calibrate(s.template_mm, s.points_mm, radial=0, tangential=False)
    res = replace(res, distortion=replace(res.distortion, k1=0.0))
    m = fit_opencv(res, pixel_um=10.0, n_coeffs=5, refine_k=False)
    intr = res.intrinsics
    assert m.camera_matrix[0, 0] == pytest.approx(intr.f_mm / 0.01)
    assert m.camera_matrix[0, 2] == pytest.approx((intr.cx_mm + 4.5) / 0.01 - 0.5)
    assert m.camera_matrix[1, 2] == pytest.approx((intr.cy_mm + 4.5) / 0.01 - 0.5)
    assert m.image_size == (900, 900)
    assert np.allclose(m.dist_coeffs, 0.0, atol=1e-12)
    assert m.fit_max_deg < 1e-9 and m.fit_max_um < 1e-9


def test_opencv_undistort_inverts_distort():
    rng = np.random.default_rng(0)
    n = rng.uniform(-0.4, 0.4, (200, 2))
    c = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01, 0.1, 0.02, 0.0])
    back = opencv_undistort(opencv_distort(n, c), c)
    assert np.allclose(back, n, atol=1e-12)


def test_folding_fit_is_refused(calibs):
    """Lens 2 (20 % distortion at the corners) is beyond 5 coefficients: refused, not written with a wrong error."""
    with pytest.raises(InputError, match="8 coefficients"):
        fit_opencv(calibs[("lens2", 0)], n_coeffs=5)


def test_cli_opencv_and_ros_files(calibs, tmp_path, capsys):
    cal = tmp_path / "c.json"
    cal.write_text(json.dumps(calibs[("lens1", 0)].to_dict()))
    out = tmp_path / "c.yaml"
    assert main(["export", str(cal), "--format", "opencv-yaml", "--pixel-um", "5", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "fit error" in text and "verdict:" in text
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    D = fs.getNode("distortion_coefficients").mat().ravel()
    m = fit_opencv(calibs[("lens1", 0)], pixel_um=5.0)
    assert np.allclose(K, m.camera_matrix) and np.allclose(D, m.dist_coeffs)
    assert fs.getNode("psdcal_fit_max_deg").real() == pytest.approx(m.fit_max_deg)
    assert fs.getNode("image_width").real() == 1800
    ros = tmp_path / "ci.yaml"
    assert main(["export", str(cal), "--format", "ros", "--pixel-um", "5", "-o", str(ros)]) == 0
    y = yaml.safe_load(ros.read_text())
    assert y["distortion_model"] == "plumb_bob" and len(y["distortion_coefficients"]["data"]) == 5
    assert np.allclose(np.reshape(y["camera_matrix"]["data"], (3, 3)), m.camera_matrix)
    assert np.allclose(np.reshape(y["rectification_matrix"]["data"], (3, 3)), np.eye(3))
    P = np.reshape(y["projection_matrix"]["data"], (3, 4))
    assert np.allclose(P[:, :3], m.camera_matrix) and np.allclose(P[:, 3], 0)
    assert (y["image_width"], y["image_height"]) == (1800, 1800)
    # a refused export overwrites nothing
    cal2 = tmp_path / "c2.json"
    cal2.write_text(json.dumps(calibs[("lens2", 0)].to_dict()))
    before = ros.read_bytes()
    assert main(["export", str(cal2), "--format", "ros", "-o", str(ros), "--force"]) == 2  # refused: folds over
    assert ros.read_bytes() == before
    assert main(["export", str(cal2), "--format", "ros", "--coeffs", "8", "-o", str(ros), "--force"]) == 0
    assert yaml.safe_load(ros.read_text())["distortion_model"] == "rational_polynomial"


# -- JSON Schema -------------------------------------------------------------------------------------------------


def _validator():
    schema = calibration_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _undescribed_keys(obj, schema, path=""):
    """Keys in ``obj`` that the schema does not describe (walks properties/items/prefixItems)."""
    out = []
    if isinstance(obj, dict):
        props = schema.get("properties")
        addl = schema.get("additionalProperties")
        for k, v in obj.items():
            if props is not None and k in props:
                out += _undescribed_keys(v, props[k], f"{path}/{k}")
            elif isinstance(addl, dict):
                out += _undescribed_keys(v, addl, f"{path}/{k}")
            elif props is not None or schema.get("type") == "object" and "properties" in schema:
                out.append(f"{path}/{k}")
    elif isinstance(obj, list) and isinstance(schema.get("items"), dict):
        for v in obj[:3]:
            out += _undescribed_keys(v, schema["items"], path + "/[]")
    return out


def _files_written_by_the_tool(tmp_path):
    """Calibration JSON files from the CLI over several model switches (both costs, aspect, skew, PSD, reject)."""
    d = tmp_path / "sim"
    assert main(["simulate", "--lens", "lens1", "--images", "8", "--l1", "-1.3e-3", "-o", str(d)]) == 0
    runs = {
        "default": [],
        "template": ["--cost", "template"],
        "psd_k3_skew": ["--psd-radial", "1", "--radial", "3", "--skew", "--no-tangential"],
        "aspect": ["--aspect", "--radial", "1"],
        "reject": ["--reject", "5"],
        "fix_prior_guess": ["--fix", "k2=0", "--prior", "f_mm=25,0.5", "--f-guess", "25", "--noise-um", "3"],
    }
    lines = (d / "points.csv").read_text().splitlines()
    f = lines[5].split(",")
    f[2] = f"{float(f[2]) + 0.05:.9f}"  # one gross outlier, for --reject to remove
    lines[5] = ",".join(f)
    (d / "points.csv").write_text("\n".join(lines) + "\n")
    files = []
    for name, extra in runs.items():
        out = tmp_path / f"{name}.json"
        assert main(["calibrate", str(d / "points.csv"), "-t", str(d / "template.csv"), "-o", str(out), "-q", *extra]) == 0
        files.append(out)
    assert json.loads((tmp_path / "reject.json").read_text())["problem"]["outlier_rejection"]["removed"]
    a = tmp_path / "amp"
    assert main(["simulate", "--lens", "lens2", "--images", "8", "--amplitudes", "--r-tol", "0.01", "--c-tol", "0.15",
                 "-o", str(a)]) == 0
    out = tmp_path / "gains.json"
    assert main(["calibrate", str(a / "points.csv"), "-t", str(a / "template.csv"), "-o", str(out), "-q",
                 "--fit-gains"]) == 0
    files.append(out)
    from psdcal.calibration.directions import simulate_sweep, sweep_grid, write_directions

    intr, dist = LENSES["lens2"]
    az, el = sweep_grid()
    write_directions(tmp_path / "sweep.csv", az, el,
                     simulate_sweep(intr, dist, [0.01, -0.02, 0.005], az, el, noise_mm=0.002, rng=1))
    out = tmp_path / "directions.json"
    assert main(["calibrate-directions", str(tmp_path / "sweep.csv"), "--distance-mm", "2000", "--fix", "k2=3e-5",
                 "-o", str(out), "-q"]) == 0
    files.append(out)
    demo = tmp_path / "demo.json"
    assert main(["demo", "-o", str(demo)]) == 0
    files.append(demo)
    return files


def test_schema_validates_every_calibration_the_tool_writes(tmp_path):
    v = _validator()
    schema = calibration_schema()
    for path in _files_written_by_the_tool(tmp_path):
        d = json.loads(path.read_text())
        errors = sorted(v.iter_errors(d), key=lambda e: list(e.absolute_path))
        assert not errors, f"{path.name}: {errors[0].message} at {list(errors[0].absolute_path)}"
        assert not _undescribed_keys(d, schema), f"{path.name}: keys not in psdcal.schema: {_undescribed_keys(d, schema)}"
        # and a round trip through the result class writes a valid file again
        again = CalibrationResult.from_dict(d).to_dict()
        assert not list(v.iter_errors(json.loads(json.dumps(again))))


def test_schema_rejects_what_breaks_the_contract(calibs):
    v = _validator()
    good = json.loads(json.dumps(calibs[("lens1", 0)].to_dict()))
    assert v.is_valid(good)
    broken = [
        ("intrinsics", lambda d: d.pop("intrinsics")),
        ("negative f", lambda d: d["intrinsics"].update(f_mm=-1.0)),
        ("string k1", lambda d: d["distortion"].update(k1="0.1")),
        ("unknown distortion key", lambda d: d["distortion"].update(k9=0.0)),
        ("negative std", lambda d: d["std"].update(f_mm=-0.1)),
        ("rvec of 2", lambda d: d["extrinsics"][0].update(rvec=[0.0, 0.0])),
        ("bad cost", lambda d: d.update(cost="plate")),
        ("radial 4", lambda d: d["model"].update(radial=4)),
        ("3 gains", lambda d: d.update(gains=[1.0, 1.0, 1.0])),
        ("covariance name", lambda d: d["covariance"].update(names=["f_mm", "zz"])),
        ("converged string", lambda d: d.update(converged="yes")),
    ]
    for what, breaker in broken:
        d = json.loads(json.dumps(good))
        breaker(d)
        assert not v.is_valid(d), what
    # a later version's extra top-level key is allowed
    d = json.loads(json.dumps(good))
    d["something_new"] = {"a": 1}
    assert v.is_valid(d)


def test_cli_json_schema(tmp_path, calibs):
    out = tmp_path / "s.json"
    assert main(["export", "--format", "json-schema", "-o", str(out)]) == 0
    assert json.loads(out.read_text()) == calibration_schema()
    bad = tmp_path / "truth.json"
    bad.write_text(json.dumps({"intrinsics": {"f_mm": 8.0, "cx_mm": 0, "cy_mm": 0, "skew": 0}}))
    out2 = tmp_path / "s2.json"
    assert main(["export", str(bad), "--format", "json-schema", "-o", str(out2)]) == 2
    assert not out2.exists()
    assert main(["export", "--format", "ros", "-o", str(out2)]) == 2
