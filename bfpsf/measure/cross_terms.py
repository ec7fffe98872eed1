"""The brighter-fatter effect of blended stars on each other: the cross terms of P(F).

`bfpsf.measure.photometry.psf_photometry` refits blended stars on the data minus
`cross_term_image`: each star's model holds its own BF, not its neighbours' charge's.
"""

import numpy as np

__all__ = ["cross_term_image"]


def _add_stamp(image, stamp, row, column):
    """Add ``stamp`` to ``image`` with its [0, 0] at (row, column), clipped at the edges."""
    rows = slice(max(row, 0), min(row + stamp.shape[0], image.shape[0]))
    columns = slice(max(column, 0), min(column + stamp.shape[1], image.shape[1]))
    if rows.start < rows.stop and columns.start < columns.stop:
        image[rows, columns] += stamp[rows.start - row:rows.stop - row,
                                      columns.start - column:columns.stop - column]


def cross_term_image(psf, table, shape):
    """BF of the fitted stars' charge on each other, e-: the model's own operator
    (`FluxDependentPSF.charge_delta`: one step or build-up, mean or exact boundary density)
    on their summed charge, minus each star's own BF term.

    G15 eq. scrambling_model is quadratic in the charge, so a blend's BF holds cross terms
    between the stars that no single-star model carries. With another operator for the sum
    than for each star, an isolated star would get a spurious term (6-8 % of its own BF for
    exact-density or build-up models with the one-step mean-density operator). Each star's
    own term is computed here with the same operator on its stamp. A table-mode model read
    back from its product has lost its density profile: its cross terms then use G15's mean
    density (the cross term itself a few percent off, no spurious term).
    """
    static, own = np.zeros(shape), np.zeros(shape)
    exact_density = psf.at().density_profile is not None
    if exact_density:
        north, east = np.zeros((shape[0] - 1, shape[1])), np.zeros((shape[0], shape[1] - 1))
    half = psf.half_size + 1
    for x_0, y_0, flux in zip(table["x_fit"], table["y_fit"], table["flux_fit"]):
        if not np.all(np.isfinite((x_0, y_0, flux))):
            continue
        model = psf.at(x_0, y_0)  # every kind: the single P(F) of this star
        column, row = int(np.rint(x_0)), int(np.rint(y_0))
        x_phase, y_phase = x_0 - column, y_0 - row
        y, x = np.mgrid[row - half:row + half + 1, column - half:column + half + 1]
        star = flux * model.evaluate_base(x - x_0, y - y_0)  # F P0, no BF
        _add_stamp(static, star, row - half, column - half)
        density = None
        if exact_density:
            density = tuple(abs(flux) * part
                            for part in model.boundary_density(x_phase, y_phase, half))
            _add_stamp(north, density[0], row - half, column - half)
            _add_stamp(east, density[1], row - half, column - half)
        # the star's own term with the same operator as the sum: an isolated star gets no
        # cross term even when the model's own term comes from a stored table whose density
        # profile is gone (a table-mode exact-density model read back from its product)
        _add_stamp(own, model.charge_delta(star, density), row - half, column - half)
    density = (north, east) if exact_density else None
    return psf.charge_delta(static, density) - own
