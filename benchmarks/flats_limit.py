"""What flats of infinite statistics give for a star's BF change on GalSim's SiliconSensor.

Issue 23's Piff target asks for the size residual slope of ``BrighterFatter`` <= 5 % of plain
Piff's with the calibration from the same sensor's flats; the acceptance measured -11.5 % with
a calibration of 32 ITL flat pairs (docs/plugins.md, "Acceptance"). GalSim builds its flats
from the areas of its pixel polygons but draws stars by landing photons, so this asks whether
the -11.5 % is the finite flats' statistical error or a floor that no number of GalSim flats
can pass.

Flats of infinite statistics measure the linear response of the pixel-polygon areas to a
charge (`silicon_area_coefficients`, on an empty image; ``--levels``: about a uniform flat
level, which the PTC model's b terms absorb). The calibration's
own solver (`solve_boundary_shifts`, electrostatic, as `bfpsf calibrate` runs it) turns them
into boundary shifts, at maxlag 4 (what ``maxlag='auto'`` picks from noise-free areas: GalSim
moves nothing beyond lag 4) and at maxlag 3 (what it picked for the acceptance's flats). Each
shift set makes a `FluxDependentPSF` whose P0 is the spots' true profile (Moffat with the
sensor's diffusion), and its BF change of sigma_x, sigma_y, T = Mxx + Myy and e1 is compared
with SiliconSensor's on the same spots (photon-shot, each minus its BF-free twin,
`simulate_spots`): the ratio of the slopes against peak, model / truth. A Piff residual slope
is 1 - ratio of plain Piff's (plain Piff leaves all of the BF change).

Rows: the flats limit; the simulator's landing shifts (`silicon_boundary_shifts`, single pixel
and scaled to the landing under a star), diagnostics; with ``--calib``, the calibration from
finite flats and its shift samples (spread of the ratio), and how far its a-matrix lies from
the flats limit in its own errors. ``--density exact``: the model's boundary density
integrated along each boundary from the profile instead of G15's mean of the two pixels
(what a P0 fitted from stars has); it matters for undersampled spots (docs/limitations.md).

    OMP_NUM_THREADS=1 python benchmarks/flats_limit.py [--calib calib.fits] \
        [--sensors lsst_itl_50_8 lsst_e2v_50_8] [--per-level 16] [--samples 30]

(about 2 minutes per sensor on one core, most of it SiliconSensor spots and landing shifts;
``--calib`` applies to the first sensor.) The same flats limit through Piff on the acceptance's
field: ``--calib calib.fits --write-calib DIR`` writes the user's calibration with its shifts
replaced by the flats limit (DIR/calib_limit3.fits, calib_limit4.fits), for
``benchmarks/bench_piff.py --control --calib DIR/calib_limit4.fits``.
"""

import argparse

import numpy as np

PEAKS_E = np.geomspace(3e3, 1.2e5, 6)
STAMP = 25
NAMES = ("sigma_x", "sigma_y", "T", "e1")


def shape_measures(stamps):
    """sigma_x, sigma_y, T = Mxx + Myy, e1 of adaptive moments (rows), NaN where flagged."""
    from bfpsf.moments.adaptive import adaptive_moments_batch

    moments = adaptive_moments_batch(np.asarray(stamps))
    mxx, myy = (np.where(moments.flags == 0, value, np.nan)
                for value in (moments.mxx, moments.myy))
    return np.array([np.sqrt(mxx), np.sqrt(myy), mxx + myy, (mxx - myy) / (mxx + myy)])


def changes(bright, faint):
    """BF changes (rows of `shape_measures`), T as the relative change dT / T."""
    bright, faint = shape_measures(bright), shape_measures(faint)
    change = bright - faint
    change[2] /= faint[2]
    return change


def profile_of(sensor, fwhm, beta):
    """The spots' profile: Moffat convolved with SiliconSensor's charge diffusion."""
    import galsim

    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma

    return galsim.Convolve(galsim.Moffat(fwhm=fwhm, beta=beta),
                           galsim.Gaussian(sigma=silicon_diffusion_sigma(sensor)))


def truth(sensor, fwhm, beta, per_level, seed):
    """SiliconSensor spots with their BF-free twins, and the slopes of their BF changes."""
    from bfpsf.measure.slopes import fit_bf_slope
    from bfpsf.validation.simulate_spots import simulate_spots

    spots = simulate_spots(sensor=sensor, fwhm=fwhm, beta=beta, peaks_e=PEAKS_E,
                           n_per_level=per_level, stamp_size=STAMP, seed=seed,
                           bf_free_twin=True)
    measured = changes(spots.stamps, spots.twin)
    return spots, [fit_bf_slope(spots.peaks, row) for row in measured]


def model_ratios(profile, shifts, spots, slopes, density="mean"):
    """Model / truth slope of each of `NAMES`: the model's P(F) - P(1) at each spot's flux and
    sub-pixel position, with the boundary ``density`` of `FluxDependentPSF.from_galsim`."""
    from bfpsf.measure.slopes import fit_bf_slope
    from bfpsf.model.psf import FluxDependentPSF

    psf = FluxDependentPSF.from_galsim(profile, shifts, oversampling=2, size=STAMP,
                                       density=density)
    rows, columns = np.mgrid[:STAMP, :STAMP]
    flux = spots.twin.sum(axis=(1, 2))
    bright = [psf.evaluate(columns, rows, f, x, y) for f, x, y in zip(flux, spots.x, spots.y)]
    faint = [psf.evaluate(columns, rows, 1.0, x, y) for x, y in zip(spots.x, spots.y)]
    model = changes(np.array(bright), np.array(faint))
    return np.array([fit_bf_slope(spots.peaks, row).slope / truth_slope.slope
                     for row, truth_slope in zip(model, slopes)])


def shift_sets(sensor, profile, maxlags, levels):
    """The flats limit at each maxlag (and about each flat level, at the largest maxlag) and
    the simulator's landing shifts, by row label."""
    from bfpsf.calibration.boundary_shifts import solve_boundary_shifts
    from bfpsf.interop.silicon_truth import silicon_area_coefficients, silicon_boundary_shifts

    area = silicon_area_coefficients(sensor, maxlag=max(8, *maxlags))  # zero beyond lag 4
    sets = {f"flats limit, maxlag {m}": solve_boundary_shifts(area[:m + 1, :m + 1],
                                                              n_samples=0).shifts
            for m in maxlags}
    m = max(maxlags)
    for level in levels:
        sets[f"flats limit, maxlag {m}, at {level / 1e3:g} ke-"] = solve_boundary_shifts(
            silicon_area_coefficients(sensor, maxlag=m, level=level), n_samples=0).shifts
    star = profile.drawImage(nx=STAMP, ny=STAMP, scale=1.0).array
    sets["landing, single pixel (diagnostic)"] = silicon_boundary_shifts(sensor)
    sets["landing under a star (diagnostic)"] = silicon_boundary_shifts(sensor, under=star)
    return sets, area


def print_row(sensor, label, ratios, spread=None):
    extra = "" if spread is None else f"   (samples: T {100 * spread[2]:.1f} %, e1 " \
                                      f"{100 * spread[3]:.1f} %)"
    print(f"{sensor:14s} {label:36s}" + "".join(f"{value:9.3f}" for value in ratios)
          + f"{100 * (1 - ratios[2]):+9.1f}{100 * (1 - ratios[3]):+9.1f}" + extra, flush=True)


def calibration_check(calib_path, area, profile, spots, slopes, n_samples, sensor):
    """The calibration from finite flats: its row, its samples' spread, and its a against the
    flats limit in its own errors."""
    from bfpsf import Calibration

    calibration = Calibration.read(calib_path)
    m = calibration.maxlag
    exact = area[:m + 1, :m + 1]
    pull = (calibration.a - exact) / calibration.a_err
    ratios = model_ratios(profile, calibration.shifts, spots, slopes)
    samples = np.array([model_ratios(profile, shifts, spots, slopes)
                        for shifts in calibration.shift_samples(limit=n_samples)])
    spread = samples.std(axis=0, ddof=1) / np.abs(ratios) if len(samples) > 1 else None
    print_row(sensor, f"from flats ({calib_path.name}, maxlag {m})", ratios, spread)
    return calibration, pull, ratios, samples


def main(argv=None):
    from pathlib import Path

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8"])
    parser.add_argument("--calib", type=Path, help="a calibration from the first sensor's flats")
    parser.add_argument("--maxlags", type=int, nargs="+", default=[3, 4])
    parser.add_argument("--levels", type=float, nargs="*", default=[5e4],
                        help="flat levels (e-) of extra flats-limit rows, about a uniform level")
    parser.add_argument("--per-level", type=int, default=16)
    parser.add_argument("--samples", type=int, default=30,
                        help="shift samples of --calib propagated (0: none)")
    parser.add_argument("--fwhm", type=float, default=3.45)
    parser.add_argument("--beta", type=float, default=3.5)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--density", choices=["mean", "exact"], default="mean",
                        help="the model's boundary density (mean: G15's and a fitted P0's; "
                             "exact: integrated along each boundary from the profile)")
    parser.add_argument("--write-calib", type=Path, metavar="DIR",
                        help="write --calib with its shifts replaced by the flats limit at each "
                             "maxlag (DIR/calib_limit<m>.fits, for bench_piff.py --calib), "
                             "and stop")
    args = parser.parse_args(argv)
    if args.write_calib is not None:
        write_limit_calibrations(args.calib, args.sensors[0], args.maxlags, args.write_calib)
        return 0
    print(f"Moffat FWHM {args.fwhm} px, beta {args.beta}, {args.density} density; peaks "
          f"{PEAKS_E[0]:.0f}-{PEAKS_E[-1]:.0f} e-, {args.per_level} spots per level; model / "
          "SiliconSensor slope of the BF change; 'left' = 1 - ratio, % of plain Piff's "
          "residual slope")
    header = "".join(f"{name:>9s}" for name in NAMES) + f"{'T left':>9s}{'e1 left':>9s}"
    print(f"{'sensor':14s} {'shifts':36s}{header}")
    for index, sensor in enumerate(args.sensors):
        profile = profile_of(sensor, args.fwhm, args.beta)
        spots, slopes = truth(sensor, args.fwhm, args.beta, args.per_level, args.seed)
        print(f"{sensor:14s} {'SiliconSensor slopes per 100 ke-':36s}"
              + "".join(f"{slope.slope:9.2e}" for slope in slopes)
              + "   (relative errors " + ", ".join(f"{abs(s.slope_err / s.slope):.1%}"
                                                 for s in slopes) + ")", flush=True)
        sets, area = shift_sets(sensor, profile, args.maxlags, args.levels)
        for label, shifts in sets.items():
            print_row(sensor, label, model_ratios(profile, shifts, spots, slopes,
                                                  args.density))
        if args.calib is not None and index == 0:
            calibration, pull, ratios, samples = calibration_check(
                args.calib, area, profile, spots, slopes, args.samples, sensor)
            print(f"  its a - flats limit, in its errors (maxlag {calibration.maxlag}, "
                  f"[dy, dx]):\n{np.array2string(pull, precision=2, suppress_small=True)}\n"
                  f"  chi2 {np.sum(pull**2):.1f} for {pull.size} lags (diagonal errors)")
            if len(samples) > 1:
                limit = model_ratios(profile, solve_limit(area, calibration), spots, slopes)
                for axis in (2, 3):
                    position = np.mean(samples[:, axis] > limit[axis])
                    print(f"  {NAMES[axis]}: flats limit at its maxlag {limit[axis]:.3f}, "
                          f"from flats {ratios[axis]:.3f}, samples {samples[:, axis].mean():.3f}"
                          f" +- {samples[:, axis].std(ddof=1):.3f} ({position:.0%} of them "
                          f"above the limit)")
    return 0


def write_limit_calibrations(calib_path, sensor, maxlags, outdir):
    """``calib_path`` with its shifts replaced by the flats limit (no shift samples): gain,
    amplifiers and everything else as the user's calibration has them."""
    import dataclasses

    from bfpsf import Calibration
    from bfpsf.calibration.boundary_shifts import solve_boundary_shifts
    from bfpsf.interop.silicon_truth import silicon_area_coefficients

    if calib_path is None:
        raise SystemExit("--write-calib needs --calib (the calibration whose shifts it replaces)")
    calibration = Calibration.read(calib_path)
    area = silicon_area_coefficients(sensor, maxlag=max(maxlags))
    outdir.mkdir(parents=True, exist_ok=True)
    for m in maxlags:
        shifts = solve_boundary_shifts(area[:m + 1, :m + 1], n_samples=0).shifts
        limit = dataclasses.replace(calibration, shifts=shifts, shifts_north_err=None,
                                    shifts_east_err=None, shift_samples_north=None,
                                    shift_samples_east=None)
        path = outdir / f"calib_limit{m}.fits"
        limit.write(path)
        print(f"wrote {path}: {calib_path.name} with the flats limit of {sensor}, maxlag {m}")


def solve_limit(area, calibration):
    """The flats limit at the calibration's maxlag, weighted with its errors."""
    from bfpsf.calibration.boundary_shifts import solve_boundary_shifts

    m = calibration.maxlag
    return solve_boundary_shifts(area[:m + 1, :m + 1], calibration.a_err, n_samples=0).shifts


if __name__ == "__main__":
    raise SystemExit(main())
