"""psdcal.report.plots: every figure builds headless, has content, and works on a calibration read back from JSON."""
import io
import json

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.figure import Figure

from psdcal.report import plots
from psdcal.calibration.core import CalibrationResult, calibrate
from psdcal.report.compare import compare
from psdcal.calibration.checks import align_to_problem, coverage, measured_points_mm
from psdcal.calibration.outliers import reject_outliers
from psdcal.study.simulate import simulate_set


@pytest.fixture(scope="module")
def result():
    s = simulate_set("lens2", n_images=6, noise_mm=0.003, seed=11)
    X = s.points_mm.copy()
    X[1, 2] += 0.15
    return reject_outliers(calibrate(s.template_mm, X), 5.0).result


def _pixels(fig):
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=60)
    return mpimg.imread(io.BytesIO(buf.getvalue()), format="png")[..., :3]


def _not_blank(img):
    dark = np.mean(np.any(img < 0.9, axis=-1))
    return img.std() > 0.05 and dark > 0.02


FIGS = ["residuals", "residuals_per_image", "residual_histogram", "per_image_rms", "coverage", "distortion_field",
        "aoa_uncertainty", "correlation"]


@pytest.mark.parametrize("name", FIGS)
def test_figure_has_content(result, name):
    fig = getattr(plots, name)(result)
    assert isinstance(fig, Figure) and fig.axes
    assert _not_blank(_pixels(fig))


def test_all_figures_and_compare_maps(result):
    figs = plots.all_figures(result)
    assert sorted(figs) == sorted(FIGS)
    fig = plots.compare_maps(compare(result, result, n=11))
    assert _not_blank(_pixels(fig))


def test_figures_from_json_with_unsorted_point_ids():
    s = simulate_set("lens2", n_images=5, noise_mm=0.003, seed=4)
    pids = [f"led{13 - j:02d}" for j in range(14)]  # not in sorted order
    r = calibrate(s.template_mm, s.points_mm, point_ids=pids)
    back = CalibrationResult.from_dict(json.loads(json.dumps(r.to_dict())))
    assert back.point_ids != r.point_ids  # the JSON reader sorts them
    al = align_to_problem(back)
    assert al.point_ids == r.point_ids
    assert np.allclose(al.residuals_mm, r.residuals_mm, equal_nan=True)
    assert measured_points_mm(al).shape == al.residuals_mm.shape
    assert _not_blank(_pixels(plots.residuals(back)))


def test_coverage_finds_the_empty_half():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-4.5, 0.0, 500), rng.uniform(-4.5, 4.5, 500)])
    c = coverage(pts, (9.0, 9.0), n_cells=6)
    assert c.counts.sum() == 500
    assert c.empty[:, 3:].all() and not c.empty[:, :3].any()
    assert c.fraction_covered == pytest.approx(0.5)
    assert "18 cell(s)" in c.warnings()[0]
    # a measurement region on the left half only is covered
    c2 = coverage(pts, (9.0, 9.0), n_cells=6, region_mm=(-4.5, 0.0, -4.5, 4.5))
    assert c2.warnings() == [] and c2.fraction_covered == 1.0
