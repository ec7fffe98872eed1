"""From a measured a-matrix (LSST cp_pipe layout) to the brighter-fatter slope of stars.

For the camera team that already has a PTC. Reads the empirical a-matrix of the LSSTCam
detector R22_S11 (E2V-CCD250-382) shipped with bfpsf (LSST cp_pipe, DM-51897; or any table in
the cp_pipe CSV layout ``i,j,a_mean_per_e,a_sigma_per_e``, ``i`` the serial lag), solves it
into boundary shifts (`bfpsf.solve_boundary_shifts`, the electrostatic model by default) and
predicts the growth of star sizes with peak flux (pixels per 100 ke- of peak) for Moffat PSFs
of several FWHM, with the flux-dependent PSF P(F).

Usage::

    python examples/cp_pipe_amatrix.py [--quick] [--amatrix FILE.csv] [--output DIR]
"""

import argparse
from pathlib import Path

import galsim
import numpy as np

import bfpsf
from bfpsf.calibration.measured import read_measured_area
from bfpsf.measure.slopes import fit_bf_slope
from bfpsf.measure.model_slopes import model_size_increments

SET, FILE = "cp_pipe_r22_s11", "amatrix_LSSTCam_R22_S11_E2V-CCD250-382.csv"


def predicted_slopes(shifts, fwhm, beta=3.5):
    """BF slopes of sigma_x and sigma_y (pix / 100 ke- of peak) a Moffat of this FWHM gets."""
    psf = bfpsf.FluxDependentPSF.from_galsim(galsim.Moffat(beta=beta, fwhm=fwhm), shifts,
                                             size=int(6 * fwhm) | 1)
    peak_fraction = psf.star_image(1.0).max()
    fluxes = np.linspace(1e4, 1.2e5, 8) / peak_fraction  # peaks 10-120 ke-
    increments = model_size_increments(psf, fluxes)
    peaks = np.array([psf.star_image(flux).max() for flux in fluxes])
    return {axis: fit_bf_slope(peaks, increments[axis]).slope for axis in ("x", "y")}, psf


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one FWHM")
    parser.add_argument("--amatrix", help="a-matrix table (default: the shipped R22_S11 one)")
    parser.add_argument("--output", default="amatrix_output", help="output directory")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    if args.amatrix is None:
        from bfpsf.data import measured_path  # the measured tables shipped with bfpsf

        path = measured_path(SET, FILE)
    else:
        path = args.amatrix
    measured = read_measured_area(path)
    area = measured.area  # [dy, dx], 1/e-
    print(f"{Path(path).name}: a(0,0) = {area[0, 0]:.3g} /e-, serial a(1,0) = {area[0, 1]:.3g}, "
          f"parallel a(0,1) = {area[1, 0]:.3g}")
    # the default solver: the electrostatic model of the sensor fitted to every lag
    solution = bfpsf.solve_boundary_shifts(area, measured.area_err, n_samples=0)
    shifts = solution.shifts
    m = shifts.radius
    print(f"boundary shifts to radius {m}: a^N(0,0) = {shifts.north[m, m]:.3g}, "
          f"a^E(0,0) = {shifts.east[m, m]:.3g} / e-")
    widths = [4.0] if args.quick else [2.5, 3.0, 3.5, 4.0, 5.0, 6.0]
    slopes = {}
    for fwhm in widths:
        slopes[fwhm], psf = predicted_slopes(shifts, fwhm)
        sigma = psf.shape(1.0).sigma
        print(f"FWHM {fwhm:.1f} px (sigma {sigma:.3f}): predicted slope sigma_x "
              f"{slopes[fwhm]['x']:.4f}, sigma_y {slopes[fwhm]['y']:.4f} pix / 100 ke- "
              f"({100 * slopes[fwhm]['x'] / sigma:.2f} %, "
              f"{100 * slopes[fwhm]['y'] / sigma:.2f} % of sigma)")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bfpsf.plotting.calibration import plot_area_matrix

    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6))
    plot_area_matrix(area, ax=left)
    right.plot(widths, [slopes[w]["x"] for w in widths], "o-", label="sigma_x (serial)")
    right.plot(widths, [slopes[w]["y"] for w in widths], "s-", label="sigma_y (parallel)")
    right.set_xlabel("Moffat FWHM (pixels)")
    right.set_ylabel("predicted slope (pix / 100 ke- of peak)")
    right.legend(fontsize=8)
    right.set_title("brighter-fatter slope predicted with P(F)", fontsize=9)
    figure.tight_layout()
    figure.savefig(output / "cp_pipe_amatrix.png", dpi=70)
    print(f"wrote {output / 'cp_pipe_amatrix.png'}")
    return slopes


if __name__ == "__main__":
    main()
