"""cp_pipe PTC interchange: a table built with lsst.ip.isr's PhotonTransferCurveDataset schema
is read, solved, exported and read back; the measured LSSTCam R22_S11 a-matrix drives it."""

from importlib import resources

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from bfpsf.calibration import calibrate_from_ptc
from bfpsf.calibration.ptc import covariance_errors, full_covariance_model
from bfpsf.cli import main
from bfpsf.errors import BFPSFInputError
from bfpsf.calibration.cp_pipe import PTC_COLUMNS, ptc_table_hdu, read_ptc_dataset, write_ptc_dataset

R22_S11 = ("measured/lsst_cp_pipe_LSSTCam_R22_S11_amatrix/"
           "amatrix_LSSTCam_R22_S11_E2V-CCD250-382.csv")


@pytest.fixture(scope="module")
def r22_s11_amatrix():
    """The measured R22_S11 a-matrix (package data, bfpsf/data/measured), cp_pipe layout
    [i = dx, j = dy], 1/e-."""
    source = resources.files("bfpsf") / "data" / R22_S11
    with source.open() as stream:  # 3 comment lines, then the column names
        rows = np.loadtxt(stream, delimiter=",", comments="#", skiprows=4)
    matrix = np.zeros((5, 5))
    for i, j, value, _ in rows:
        matrix[int(i), int(j)] = value
    return matrix


GAIN = 1.6
NOISE_E = 6.0
NPIX = 2000 * 500  # one LSSTCam amplifier


def cp_pipe_table(amplifiers, *, seed=0):
    """A PTC table with the PhotonTransferCurveDataset schema (ptcDataset.py, toTable), from
    the A+19 model of each amplifier's a-matrix (cp_pipe layout) plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for name, (cp_a, gain) in amplifiers.items():
        side = cp_a.shape[0]
        a = cp_a.T  # bfpsf [dy, dx]
        mean_adu = np.linspace(1e3, 9e4, 25) / gain
        noise = np.zeros((side, side))
        noise[0, 0] = NOISE_E**2
        truth = full_covariance_model(mean_adu, a, np.zeros_like(a), noise, gain)
        npix = np.full(truth.shape, float(NPIX))
        sigma = covariance_errors(truth, npix)
        cov = truth + rng.normal(size=truth.shape) * sigma
        sigma = covariance_errors(cov, npix)  # cp_pipe weights by the measured variance
        count = mean_adu.size
        nan_matrix = np.full(side * side, np.nan)
        row = {
            "AMPLIFIER_NAME": name, "PTC_FIT_TYPE": "FULLCOVARIANCE", "COV_MATRIX_SIDE": side,
            "INPUT_EXP_ID_PAIRS": np.arange(2 * count).reshape(count, 2),
            "EXP_ID_MASK": np.ones(count, dtype=bool), "RAW_EXP_TIMES": mean_adu / 1e3,
            "RAW_MEANS": mean_adu, "RAW_VARS": cov[:, 0, 0], "GAIN": gain, "GAIN_ERR": 0.0,
            "NOISE": NOISE_E, "NOISE_ERR": 0.0, "HIST_VARS": np.full(count, np.nan),
            "HIST_CHI2_DOFS": np.full(count, np.nan), "KS_PVALUES": np.zeros(count),
            "PTC_FIT_PARS": np.full(3, np.nan), "PTC_FIT_PARS_ERROR": np.full(3, np.nan),
            "PTC_FIT_CHI_SQ": np.nan, "PTC_TURNOFF": mean_adu[-1], "A_MATRIX": cp_a.ravel(),
            "B_MATRIX": np.zeros(side * side), "A_MATRIX_NO_B": nan_matrix,
            "NOISE_MATRIX": noise.T.ravel(), "NOISE_MATRIX_NO_B": nan_matrix,
            "BAD_AMPS": np.array([], dtype="U3"), "PHOTO_CHARGE": np.full(count, np.nan),
            # cp_pipe's covariance arrays are [flux, i = dx, j = dy]
            "COVARIANCES": cov.transpose(0, 2, 1).ravel(),
            "COVARIANCES_MODEL": np.full(cov.size, np.nan),
            "COVARIANCES_SQRT_WEIGHTS": (1 / sigma).transpose(0, 2, 1).ravel(),
            "COVARIANCES_MODEL_NO_B": np.full(cov.size, np.nan),
            "FINAL_VARS": cov[:, 0, 0], "FINAL_MODEL_VARS": np.full(count, np.nan),
            "FINAL_MEANS": mean_adu,
        }
        rows.append([row[column] for column in PTC_COLUMNS])
    table = Table(rows=rows, names=PTC_COLUMNS)
    table.meta.update({"OBSTYPE": "PTC", "PTC_VERSION": 1.4, "PTC_FIT_TYPE": "FULLCOVARIANCE"})
    return table


@pytest.fixture(scope="module")
def ptc_file(tmp_path_factory, r22_s11_amatrix):
    path = tmp_path_factory.mktemp("ptc") / "ptc.fits"
    skewed = r22_s11_amatrix * 1.1
    table = cp_pipe_table({"C10": (r22_s11_amatrix, GAIN), "C11": (skewed, 1.3)})
    fits.HDUList([fits.PrimaryHDU(), ptc_table_hdu(table)]).writeto(path)
    return path, {"C10": (r22_s11_amatrix, GAIN), "C11": (skewed, 1.3)}


def test_reader_transposes_cp_pipe_matrices(ptc_file):
    path, truth = ptc_file
    dataset = read_ptc_dataset(path)
    assert list(dataset) == ["C10", "C11"]
    cp_a = truth["C10"][0]
    # cp_pipe a[i = 1, j = 0] is the serial neighbour a(dx=1, dy=0) = bfpsf a[dy=0, dx=1]
    assert dataset["C10"].a[0, 1] == cp_a[1, 0] and dataset["C10"].a[1, 0] == cp_a[0, 1]
    assert dataset["C10"].gain == GAIN and dataset["C10"].data.cov_adu.shape == (25, 5, 5)
    np.testing.assert_allclose(dataset["C10"].data.npix, NPIX, rtol=1e-9)


def test_round_trip_read_solve_export_read(ptc_file, tmp_path):
    path, truth = ptc_file
    detector = calibrate_from_ptc(path, maxlag=4, n_monte_carlo=20)
    assert detector.names == ["C10", "C11"]
    for name, (cp_a, gain) in truth.items():
        one = detector[name]
        a = cp_a.T
        pulls = (one.a - a) / one.a_err
        print(name, "gain pull", (one.gain - gain) / one.gain_err, "a pulls", pulls[:2, :2])
        assert abs(one.gain - gain) < 3 * one.gain_err
        assert np.all(np.abs(pulls) < 4)  # 25 lags: the largest of 25 normal pulls
        assert one.shifts is not None and one.amplifier == name
        assert one.parameters["cp_pipe_a00"] == cp_a[0, 0]
    exported = tmp_path / "bfpsf_ptc.fits"
    write_ptc_dataset(exported, detector)
    back = read_ptc_dataset(exported)
    for name in truth:
        one = detector[name]
        np.testing.assert_array_equal(back[name].a, one.a)
        np.testing.assert_array_equal(back[name].data.cov_adu, one.covariances_adu)
        np.testing.assert_allclose(back[name].data.npix, one.npix, rtol=1e-12)
        assert back[name].gain == one.gain and back[name].noise_e == one.noise_e
    again = calibrate_from_ptc(exported, maxlag=4, n_monte_carlo=20)
    for name in truth:
        np.testing.assert_allclose(again[name].a, detector[name].a, rtol=1e-6, atol=1e-12)
        assert again[name].gain == pytest.approx(detector[name].gain, rel=1e-9)


def test_from_ptc_on_the_command_line(ptc_file, tmp_path, capsys):
    path, _ = ptc_file
    code = main(["calibrate", "--from-ptc", str(path), "--amp", "C11", "--maxlag", "3",
                 "--n-monte-carlo", "10", "-o", str(tmp_path / "cal.fits"),
                 "--export-ptc", str(tmp_path / "out_ptc.fits")])
    assert code == 0, capsys.readouterr().err
    assert list(read_ptc_dataset(tmp_path / "out_ptc.fits")) == ["C11"]


def test_not_a_ptc_table_is_refused(tmp_path):
    path = tmp_path / "other.fits"
    Table({"x": [1.0]}, meta={"OBSTYPE": "FLAT"}).write(path)
    with pytest.raises(BFPSFInputError) as error:
        read_ptc_dataset(path)
    assert str(error.value) == f"{path}: OBSTYPE is 'FLAT', not 'PTC': not a cp_pipe PTC dataset"
