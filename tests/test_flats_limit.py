"""Flats of infinite statistics on SiliconSensor ``lsst_itl_50_8``: the size BF change of a star.

GalSim builds flats from the areas of its pixel polygons and draws stars by landing photons.
Noise-free flats measure the polygon areas' response (`silicon_area_coefficients`); the
calibration's solver turns it into shifts (maxlag 4: what ``maxlag='auto'`` takes from
noise-free areas). Their P(F) over-predicts SiliconSensor's BF growth of T = Mxx + Myy by
3.5 % (FWHM 3.45 px; 3.7-5.0 % for FWHM 3.0-3.9, benchmarks/flats_limit.py with 96 spots):
the floor of the user path on this simulator, below the calibration's statistical error from
the acceptance's 32 flat pairs (11.5 %, docs/plugins.md).
"""

import os

import numpy as np

from test_gridded_silicon import shape_measures

SENSOR = "lsst_itl_50_8"
FWHM, BETA = 3.45, 3.5


def test_flats_limit_of_the_size_change_quick():
    """18 spots with their BF-free twins at 3 peaks: model / SiliconSensor slope of T."""
    import galsim

    os.environ["OMP_NUM_THREADS"] = "1"
    from bfpsf.calibration.boundary_shifts import solve_boundary_shifts
    from bfpsf.interop.silicon_truth import silicon_area_coefficients, silicon_diffusion_sigma
    from bfpsf.measure.slopes import fit_bf_slope
    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.validation.simulate_spots import simulate_spots

    spots = simulate_spots(sensor=SENSOR, fwhm=FWHM, beta=BETA, peaks_e=(1e4, 4e4, 1.2e5),
                           n_per_level=6, stamp_size=25, seed=5, bf_free_twin=True)
    shifts = solve_boundary_shifts(silicon_area_coefficients(SENSOR, maxlag=4),
                                   n_samples=0).shifts
    profile = galsim.Convolve(galsim.Moffat(fwhm=FWHM, beta=BETA),
                              galsim.Gaussian(sigma=silicon_diffusion_sigma(SENSOR)))
    psf = FluxDependentPSF.from_galsim(profile, shifts, oversampling=2, size=25)
    rows, columns = np.mgrid[:25, :25]
    flux = spots.twin.sum(axis=(1, 2))
    bright = np.array([psf.evaluate(columns, rows, f, x, y)
                       for f, x, y in zip(flux, spots.x, spots.y)])
    faint = np.array([psf.evaluate(columns, rows, 1.0, x, y) for x, y in zip(spots.x, spots.y)])

    def size(stamps):
        sigma_x, sigma_y = shape_measures(stamps)[:2]
        return sigma_x**2 + sigma_y**2

    measured = fit_bf_slope(spots.peaks, size(spots.stamps) / size(spots.twin) - 1)
    model = fit_bf_slope(spots.peaks, size(bright) / size(faint) - 1)
    ratio = model.slope / measured.slope
    error = measured.slope_err / measured.slope
    print(f"flats limit / SiliconSensor slope of dT/T: {ratio:.4f} +- {error:.4f}")
    assert error < 0.015  # 18 paired spots: 0.6-1.1 % on seeds 5, 6, 8, 9
    # over-predicts (the polygon areas' far lags exceed the landing's), by 3.5 % (module
    # notes): within 3 sigma of it, and apart from 1 (no floor) and from 1.10 (the
    # calibration from the acceptance's flats) by more than 3 sigma
    assert abs(ratio - 1.035) < 3 * error
    assert 1.0 + 3 * error < ratio < 1.10 - 3 * error
