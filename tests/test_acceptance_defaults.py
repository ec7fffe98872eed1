"""Acceptance of the defaults on sets never used in development (issue 21, item 6).

Every figure comes from the README's commands with no extra option (``bfpsf psf IMAGE...
--calib CALIB.fits -o PSF.fits``, ``bfpsf photometry IMAGE... --psf PSF.fits -o PHOT.ecsv``,
``bfpsf measure`` and ``bfpsf slope --psf``), on GalSim SiliconSensor stars (E2V,
photon-shot: the brighter-fatter truth) with the calibration of simulated flats
(`e2v_flats_calibration`: electrostatic shifts, no simulator truth), gain 1.5 e-/ADU, read
noise 5 e-, peaks 3-120 ke-. Seeds 7301-7305 were never used before these figures were taken.

Sets: a constant sky (300 e-); a sloped sky of its own in every exposure (20-610 e-); a dense
field (stars 9 pixels apart at least, blends); a Kolmogorov atmosphere convolved with an
optical PSF (wings unlike a Moffat's, sloped sky; drawn without the sensor, the flats' shifts
applied by bfpsf: photon shooting it takes too long); a PSF varying over the field (FWHM
3.0 -> 3.9 px along x, ``psf --grid 3 3``). Reproduce: ``OMP_NUM_THREADS=1 python -m pytest --runslow
-s tests/test_acceptance_defaults.py`` (about 6 minutes); the quick variant in CI is
tests/test_defaults_matrix.py.
"""

import json

import galsim
import numpy as np
import pytest
from astropy.table import Table

from bfpsf.cli import main
from bfpsf.validation.simulate_fields import kolmogorov_optical, simulate_field
from bfpsf.validation.simulate_spots import write_image_adu

GAIN = 1.5
MOFFAT = galsim.Moffat(beta=3.5, fwhm=3.45)
SHAPE = (320, 320)


def _varying(x, y):
    return galsim.Moffat(beta=3.5, fwhm=3.0 + 0.9 * x / (SHAPE[1] - 1))


#: name -> (profile, simulate_field options, bfpsf psf options)
SETS = {
    "constant sky": (MOFFAT, dict(sky_range_e=(300.0, 300.0), seed=7301), []),
    "sloped sky": (MOFFAT, dict(seed=7302), []),
    "dense field": (MOFFAT, dict(n_stars=140, min_separation=9.0, seed=7303), []),
    # photon-shooting an OpticalPSF through the SiliconSensor takes more than 10 minutes for
    # 180 stars: drawn without the sensor, with the flats' shifts applied by bfpsf; each star
    # on 201^2 pixels, so that the truth holds its whole wings (a 64-pixel stamp leaves out
    # 0.8 % of the flux, which the sky fit, modelling the wings to 75 pixels, then takes
    # out of the sky: -2 e-, -5 mmag)
    "Kolmogorov x optics": (kolmogorov_optical(), dict(seed=7304, sensor=None, stamp=201),
                            []),
    "varying PSF (--grid 3 3)": (_varying, dict(n_stars=70, min_separation=25.0, seed=7305),
                                 ["--grid", "3", "3"]),
}


def _photometry_figures(table, field, images):
    """Mean offset from the true total flux and bright-minus-faint drift, mmag, with errors."""
    magnitudes, peaks = [], []
    for index, path in enumerate(images):
        mine, truth = table[table["image"] == path], field.truth[index]
        distance = np.hypot(np.asarray(mine["x_fit"])[:, None] - truth["x"],
                            np.asarray(mine["y_fit"])[:, None] - truth["y"])
        nearest, matched = distance.argmin(axis=1), distance.min(axis=1) < 1.0
        clean = matched & (np.asarray(mine["flags"]) == 0)
        magnitudes.append(-2.5e3 * np.log10(np.asarray(mine["flux_fit"])[clean]
                                            / truth["flux_e"][nearest[clean]]))
        peaks.append(truth["peak_e"][nearest[clean]])
    magnitudes, peaks = np.concatenate(magnitudes), np.concatenate(peaks)
    # brightest and faintest fifths of the peaks (log-uniform 3-120 ke-: about 3-6 ke- and
    # 60-120 ke-)
    low, high = np.quantile(peaks, [0.2, 0.8])
    faint, bright = magnitudes[peaks <= low], magnitudes[peaks >= high]

    def error(values):
        return 1.2533 * 1.4826 * np.median(np.abs(values - np.median(values))) / np.sqrt(
            values.size)

    return {"n": int(magnitudes.size),
            "mean": float(np.median(magnitudes)), "mean_err": float(error(magnitudes)),
            "drift": float(np.median(bright) - np.median(faint)),
            "drift_err": float(np.hypot(error(bright), error(faint)))}


def run_defaults(field, calibration, directory, psf_options=()):
    """The README's ``bfpsf psf`` and ``bfpsf photometry`` with no option on a simulated
    field (its images written in ADU with gain `GAIN`, the calibration beside them in
    ``directory``): (`_photometry_figures`, the psf JSON summary, the image paths)."""
    calibration.write(directory / "calib.fits")
    images = []
    for index, image in enumerate(field.images):
        images.append(str(directory / f"image{index}.fits"))
        write_image_adu(images[-1], image, gain=GAIN)
    calib, psf = str(directory / "calib.fits"), str(directory / "psf.fits")
    assert main(["psf", *images, "--calib", calib, "-o", psf, "--json",
                 str(directory / "psf.json"), *psf_options]) == 0
    assert main(["photometry", *images, "--psf", psf, "-o", str(directory / "phot.ecsv"),
                 "--json", str(directory / "phot.json")]) == 0
    figures = _photometry_figures(Table.read(directory / "phot.ecsv"), field, images)
    return figures, json.loads((directory / "psf.json").read_text()), images


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SETS))
def test_defaults_on_unseen_sets(name, e2v_flats_calibration, tmp_path):
    profile, options, psf_options = SETS[name]
    options = dict(dict(n_images=3, shape=SHAPE, n_stars=60, min_separation=28.0,
                        sensor="lsst_e2v_50_8"), **options)
    if options["sensor"] is None:
        options["shifts"] = e2v_flats_calibration.shifts
    field = simulate_field(profile, **options)
    figures, summary, images = run_defaults(field, e2v_flats_calibration, tmp_path,
                                            psf_options)
    calib, psf = str(tmp_path / "calib.fits"), str(tmp_path / "psf.fits")
    # e- are ADU times the calibrated gain, which the flats know to its own error: every flux
    # and sky carries it (the first figure); the photometry's own offset is the second
    scale = e2v_flats_calibration.gain / GAIN
    gain_mmag = -2500 * np.log10(scale)
    # the wings fit keeps the sky surface the images show: a constant where the sky is one
    degrees = [entry["sky_degree"] for entry in summary["images"]]
    if name in ("constant sky", "sloped sky"):
        assert degrees == [int(name == "sloped sky")] * len(degrees), degrees
    assert abs(scale - 1) < 3 * e2v_flats_calibration.gain_err / GAIN
    sky_errors = [entry["background_e"] - scale * sky[0]
                  for entry, sky in zip(summary["images"], field.skies)]
    photometry = json.loads((tmp_path / "phot.json").read_text())
    sky_errors_photometry = [entry["background_e"] - scale * sky[0]
                             for entry, sky in zip(photometry["images"], field.skies)]
    print(f"\n[{name}] {figures['n']} stars: mean offset from the true total flux "
          f"{figures['mean']:+.2f} +- {figures['mean_err']:.2f} mmag (the gain's "
          f"{gain_mmag:+.2f}; the photometry's {figures['mean'] - gain_mmag:+.2f}), brightest - "
          f"faintest {figures['drift']:+.2f} +- {figures['drift_err']:.2f} mmag; "
          f"flux_correction {summary['flux_correction']:.4f} +- "
          f"{summary['flux_correction_err']:.4f}; sky at the centre - truth (in the "
          f"calibration's e-) {', '.join(f'{value:+.2f}' for value in sky_errors)} e- (psf), "
          f"{', '.join(f'{value:+.2f}' for value in sky_errors_photometry)} e- (photometry)")
    if psf_options:
        assert main(["measure", *images, "--calib", calib, "-o",
                     str(tmp_path / "stars.ecsv")]) == 0
        assert main(["slope", str(tmp_path / "stars.ecsv"), "--psf", psf, "--json",
                     str(tmp_path / "slope.json")]) == 0
        slope = json.loads((tmp_path / "slope.json").read_text())
        for axis in ("x", "y", "e1", "e2"):
            # the residual: each star minus the model at its own flux, position and phase;
            # its error with the calibration's (the product's shift samples)
            raw, residual = slope[axis], slope["model_residual"][axis]
            error = residual["slope_err_total"]
            print(f"[{name}] slope --psf {axis}: raw {raw['slope']:+.5f} +- "
                  f"{raw['slope_err']:.5f}, predicted {slope['prediction'][axis]['slope']:+.5f}"
                  f", residual {residual['slope']:+.5f} +- {residual['slope_err']:.5f} "
                  f"(+- {error:.5f} with the calibration's; "
                  f"{100 * residual['slope'] / raw['slope']:+.1f} % of raw)")
            if axis in ("x", "y"):
                # issue 21: size residual within 2 % of raw (and its error)
                assert abs(residual["slope"]) <= 0.02 * abs(raw["slope"]) + 2 * error
            elif axis == "e1":
                # the grid's P0 e1 errors (rms 0.003 at the stars) are in this error; e2, where
                # the model predicts no BF change, shows what they do alone (docs/defaults.md)
                assert abs(residual["slope"]) <= max(2 * error, 0.2 * abs(raw["slope"]))
    # issue 21 targets: mean offset <= 3 mmag (the gain's error apart), brightest - faintest
    # <= 1 mmag (each with its 2-sigma statistical error: 180 stars, the faintest fifth's
    # noise 1-2 mmag per star)
    assert abs(figures["mean"] - gain_mmag) <= 3.0 + 2 * figures["mean_err"]
    assert abs(figures["drift"]) <= 1.0 + 2 * figures["drift_err"]
