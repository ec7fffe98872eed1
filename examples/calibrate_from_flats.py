"""Calibrate brighter-fatter from flat-field pairs: the photon transfer curve and a(dx, dy).

For the detector engineer. Simulates flat pairs of a GalSim SiliconSensor (ITL) in ADU,
writes them as FITS files, calibrates them as a user would with their own flats
(`bfpsf.calibrate`: covariances, PTC fit, boundary shifts), compares the gain and the area
coefficients a(dx, dy) with the sensor's truth, and draws the PTC and the a-matrix.

Usage::

    python examples/calibrate_from_flats.py [--quick] [--output DIR]

``--quick`` uses small flats (seconds); the default takes a few minutes. With your own flats:
``bfpsf calibrate FLAT.fits... -o CALIB.fits --plots DIR``.
"""

import argparse
from pathlib import Path

import numpy as np

import bfpsf
from bfpsf.interop.silicon_truth import silicon_area_coefficients
from bfpsf.validation.simulate_flats import write_flats

GAIN = 1.5  # e-/ADU of the simulated camera
SENSOR = "lsst_itl_50_8"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small flats, seconds")
    parser.add_argument("--output", default="calibrate_output", help="output directory")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)

    if args.quick:
        levels, size, pairs, maxlag = [100.0, 2e4, 4e4, 6e4, 8e4, 1e5, 1.3e5, 1.6e5], 64, 1, 3
    else:
        levels, size, pairs, maxlag = list(np.linspace(1e3, 1.6e5, 16)), 256, 2, 4
    flats = write_flats(output / "flats", SENSOR, levels, size=size, pairs=pairs,
                        nsteps=10 if args.quick else 20, gain=GAIN, seed=3, overwrite=True)
    print(f"{len(flats)} flats of {size}^2 pixels at {len(levels)} levels in {output / 'flats'}")

    calibration = bfpsf.calibrate(flats, maxlag=maxlag, n_monte_carlo=20 if args.quick else 200)
    truth = silicon_area_coefficients(SENSOR, maxlag=maxlag)
    print(f"gain {calibration.gain:.4f} +- {calibration.gain_err:.4f} e-/ADU (true {GAIN})")
    print("a(dx, dy) [1e-7 / e-]   measured            truth")
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        print(f"  ({dx}, {dy})              {calibration.a[dy, dx] * 1e7:+7.3f} +- "
              f"{calibration.a_err[dy, dx] * 1e7:5.3f}   {truth[dy, dx] * 1e7:+7.3f}")
    calibration.write(output / "calib.fits", overwrite=True)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bfpsf.plotting.calibration import plot_area_matrix, plot_ptc

    figure, (left, middle, right) = plt.subplots(1, 3, figsize=(13, 3.8))
    plot_ptc(calibration, ax=left)
    top = float(max(truth[1:, :].max(), truth[0, 1:].max()))  # one colour scale
    plot_area_matrix(calibration.a, ax=middle, vmin=-0.2 * top, vmax=top,
                     title=f"measured a(dx, dy), a(0,0) = {calibration.a[0, 0] * 1e7:.1f}e-7")
    plot_area_matrix(truth, ax=right, vmin=-0.2 * top, vmax=top,
                     title=f"SiliconSensor truth, a(0,0) = {truth[0, 0] * 1e7:.1f}e-7")
    figure.tight_layout()
    figure.savefig(output / "calibrate_from_flats.png", dpi=70)
    print(f"wrote {output / 'calib.fits'} and {output / 'calibrate_from_flats.png'}")
    return calibration, truth


if __name__ == "__main__":
    main()
