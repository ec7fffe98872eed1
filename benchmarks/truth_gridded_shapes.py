"""A gridded PSF product against GalSim truth: P0 and the BF change of size and e1 at (x, y).

For the acceptance's varying PSF (tests/test_acceptance_defaults.py, "varying PSF (--grid 3
3)": Moffat beta 3.5, FWHM 3.0 -> 3.9 px along x over 320 pixels): SiliconSensor
``lsst_e2v_50_8`` stars at 9 positions (7 along x at the centre line, 2 at the bottom and top
edges), each drawn again with BF switched off and the same photons (its twin,
`simulate_spots`), at peaks of 4 and 100 ke-. The model (`psf.evaluate` at the star's flux,
position and sub-pixel phase, as `bfpsf.moments.shapes.psf_shapes`) is compared with them:

- P0: twin minus the model at unit flux (sigma_x, sigma_y, e1, e2), per position;
- BF change of the bright stars: star minus twin against the model's P(F) - P(1), with the
  product's shifts and with the simulator's own (`silicon_boundary_shifts` under a star, a
  diagnostic), per position and in the mean.

Run (about a minute of SiliconSensor): ``OMP_NUM_THREADS=1 python
benchmarks/truth_gridded_shapes.py PSF.fits [--stars 6]``, PSF.fits from the acceptance set
(``pytest --runslow tests/test_acceptance_defaults.py -k varying --basetemp DIR``).
"""

import argparse

import numpy as np

SENSOR = "lsst_e2v_50_8"
LENGTH = 320
HALF = 12
POSITIONS = [(x, 160) for x in (12, 60, 100, 160, 220, 260, 307)] + [(160, 12), (160, 307)]


def measures(stamps):
    """sigma_x, sigma_y, e1, e2 (rows) of adaptive moments."""
    from bfpsf.moments.adaptive import adaptive_moments_batch
    from bfpsf.moments.shapes import distortion

    moments = adaptive_moments_batch(np.asarray(stamps))
    return np.array([np.sqrt(moments.mxx), np.sqrt(moments.myy),
                     *distortion(moments.mxx, moments.myy, moments.mxy)])


def draw(n_stars):
    """Stars and twins cut to 25^2 around each, with their image position and flux."""
    from bfpsf.validation.simulate_spots import simulate_spots

    rows = []
    for index, (x, y) in enumerate(POSITIONS):
        spots = simulate_spots(sensor=SENSOR, fwhm=3.0 + 0.9 * x / (LENGTH - 1), beta=3.5,
                               peaks_e=(4e3, 1e5), n_per_level=n_stars, stamp_size=40,
                               seed=1000 + index, bf_free_twin=True)
        for star in range(len(spots.x)):
            column, row = int(np.rint(spots.x[star])), int(np.rint(spots.y[star]))
            cut = np.s_[row - HALF:row + HALF + 1, column - HALF:column + HALF + 1]
            rows.append(dict(position=(x, y), x=x + spots.x[star] - column,
                             y=y + spots.y[star] - row, bright=bool(spots.level[star]),
                             flux=float(spots.twin[star].sum()), star=spots.stamps[star][cut],
                             twin=spots.twin[star][cut]))
    return rows


def model_measures(psf, rows, unit_flux=False):
    stamps = []
    offsets = np.arange(-HALF, HALF + 1)
    for row in rows:
        columns, lines = np.meshgrid(offsets + np.rint(row["x"]), offsets + np.rint(row["y"]))
        stamps.append(psf.evaluate(columns, lines, 1.0 if unit_flux else row["flux"],
                                   row["x"], row["y"]))
    return measures(stamps)


def main():
    import galsim

    from bfpsf.interop.silicon_truth import silicon_boundary_shifts, silicon_diffusion_sigma
    from bfpsf.model.psf import FluxDependentPSF

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("psf", metavar="PSF.fits")
    parser.add_argument("--stars", type=int, default=6, help="stars per position and peak")
    args = parser.parse_args()
    psf = FluxDependentPSF.read(args.psf)
    charge = galsim.Convolve(galsim.Moffat(fwhm=3.45, beta=3.5),
                             galsim.Gaussian(sigma=silicon_diffusion_sigma(SENSOR)))
    simulator = psf.with_shifts(silicon_boundary_shifts(
        SENSOR, under=charge.drawImage(nx=25, ny=25, scale=1.0).array))
    rows = draw(args.stars)
    star, twin = measures([r["star"] for r in rows]), measures([r["twin"] for r in rows])
    unit = model_measures(psf, rows, unit_flux=True)
    change = {"product's shifts": model_measures(psf, rows) - unit,
              "simulator's shifts": model_measures(simulator, rows)
              - model_measures(simulator, rows, unit_flux=True)}
    names = ("sigma_x", "sigma_y", "e1", "e2")
    position = np.array([r["position"] for r in rows])
    bright = np.array([r["bright"] for r in rows])

    def mean(values):
        return f"{np.mean(values):+.4f} +- {np.std(values) / np.sqrt(values.size):.4f}"

    print("P0, twin minus model at unit flux:")
    for where in POSITIONS:
        members = np.all(position == where, axis=1)
        print(f"  {where}: " + ", ".join(f"{name} {mean(twin[axis, members] - unit[axis, members])}"
                                         for axis, name in enumerate(names)))
    print("BF change of the bright stars (truth: star - twin; model: P(F) - P(1)):")
    for axis, name in enumerate(names[:3]):
        truth = star[axis, bright] - twin[axis, bright]
        print(f"  {name}: truth {truth.mean():+.5f} +- "
              f"{truth.std() / np.sqrt(truth.size):.5f}; " + "; ".join(
                  f"model with the {label} {values[axis, bright].mean():+.5f}"
                  for label, values in change.items()))


if __name__ == "__main__":
    main()
