"""Every script of examples/ runs in its quick mode and gives the physics it shows."""

import importlib.util
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run_example(name, tmp_path, *extra):
    """Import examples/<name>.py as a module and run its main() with --quick."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    result = module.main(["--quick", "--output", str(tmp_path), *extra])
    figures = list(tmp_path.glob("*.png"))
    assert figures, "the example draws its figure"
    for figure in figures:
        assert 5_000 < figure.stat().st_size < 200_000
    return result


def test_calibrate_from_flats(tmp_path):
    calibration, truth = run_example("calibrate_from_flats", tmp_path)
    assert calibration.gain == pytest.approx(1.5, abs=4 * calibration.gain_err)
    # 16 flats of 64^2: a(0,0) to about 30 %
    assert abs(calibration.a[0, 0] - truth[0, 0]) < 3 * calibration.a_err[0, 0]
    assert (tmp_path / "calib.fits").is_file()


def test_crowded_field_photometry(tmp_path):
    results = run_example("crowded_field_photometry", tmp_path)
    for result in results.values():
        assert result["good"].mean() > 0.9
        # every star within 5 % (blends included): the fits are sane
        assert np.median(np.abs(result["ratio"][result["good"]] - 1)) < 0.05


def test_shear_psf_size(tmp_path):
    result = run_example("shear_psf_size", tmp_path)
    assert result["bright"].sigma > 1.01 * result["faint"].sigma
    # the bias of the bright stars' PSF: positive, within 20 % of dT_psf / T_gal
    np.testing.assert_allclose(result["m"], result["m_first_order"], rtol=0.2)
    assert np.all(result["m"] > 0.01)


def test_simulate_with_bf(tmp_path):
    measured, predicted = run_example("simulate_with_bf", tmp_path)
    for slopes in measured.values():
        for axis in ("x", "y"):
            assert abs(slopes[axis].slope - predicted[axis]) < 4 * slopes[axis].slope_err


def test_cp_pipe_amatrix(tmp_path):
    slopes = run_example("cp_pipe_amatrix", tmp_path)
    for value in slopes.values():
        # E2V: the parallel neighbour a(0,1) is larger, so sigma_y grows faster
        assert 0 < value["x"] < value["y"]


def test_measured_shifts(tmp_path, capsys):
    """The published ITL-3800C-002 table through G15's Ei solver and the electrostatic one."""
    spec = importlib.util.spec_from_file_location("example_measured_shifts",
                                                  EXAMPLES / "measured_shifts.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--quick", "--output", str(tmp_path)])
    out = capsys.readouterr().out
    assert "ITL-3800C-002" in out and "electrostatic" in out
    assert list(tmp_path.glob("*.png"))


def test_docs_figures_are_stamped_with_their_command(tmp_path):
    """docs/make_figures.py runs a figure's command and writes it with a footer naming the
    command, version, commit and date: the image grows by the footer, the rest unchanged."""
    spec = importlib.util.spec_from_file_location(
        "make_figures", EXAMPLES.parent / "docs" / "make_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert set(module.FIGURES) >= {path.stem for path in (EXAMPLES.parent / "docs" /
                                                          "examples").glob("*.png")}
    written = module.make_figure("cp_pipe_amatrix", tmp_path, quick=True)
    stamped = matplotlib.image.imread(written)
    original = matplotlib.image.imread(EXAMPLES.parent / "docs" / "examples" / written.name)
    assert stamped.shape[1] == original.shape[1]
    footer = stamped[-module.FOOTER_PIXELS:, :, :3]
    assert footer.min() < 0.6 and np.median(footer) == 1.0  # dark text on white
