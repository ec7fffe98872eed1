"""The light of a star beyond the PSF's support: its profile, `WingModel`, and the glow of a
set of stars, `wing_image`.

P0 is normalised inside its support: the light beyond it is each PSF product's wing profile
(``wing_coefficients``, ``wing_tail_power``), W(r) per unit of the flux P0 holds, measured
from the images' stars with their skies (`bfpsf.measure.total_flux.fit_sky_and_wings`). Its
integral beyond the support is the product's ``flux_correction - 1``; its glow is what the
sky estimate subtracts (`bfpsf.measure.sky.estimate_sky`).
"""

from dataclasses import dataclass

import numpy as np

__all__ = ["WingModel", "node_basis", "node_radii", "wing_image"]

#: Outer radius of the wings fitted and of a star's glow (`wing_image`), in support
#: half-widths.
GLOW = 6.0

#: Nodes of the wing profile, log-spaced from the support's edge to `GLOW` half-widths.
WING_NODES = 6

#: Power of the wing shape the node coefficients multiply (W = c(r) r^-3): an obscured
#: telescope's diffraction aureole; a Kolmogorov atmosphere's r^-11/3 and a Moffat's r^-2beta
#: are in the coefficients' run with radius.
BASE_POWER = 3.0


def node_radii(half_size):
    """The radii (pixels) of the `WING_NODES` nodes for a support half-width."""
    inner = half_size + 0.5
    return inner * GLOW ** (np.arange(WING_NODES) / (WING_NODES - 1))


def node_basis(radius, half_size):
    """The node basis at ``radius``: linear interpolation in log r between the nodes (1 at
    its own node, 0 at its neighbours; constant inwards of the first node), times r^-3;
    zero beyond the last node. Shape (nodes, radius.size)."""
    nodes = np.log(node_radii(half_size))
    log_r = np.log(np.maximum(np.asarray(radius, dtype=float), 1.0))
    step = nodes[1] - nodes[0]
    hats = np.clip(1.0 - np.abs(log_r[None, :] - nodes[:, None]) / step, 0.0, 1.0)
    hats[0, log_r < nodes[0]] = 1.0
    hats[:, log_r > nodes[-1]] = 0.0
    return hats * np.exp(-BASE_POWER * log_r)[None, :]


@dataclass(frozen=True)
class WingModel:
    """A star's light beyond the PSF support, per unit of the flux inside it.

    W(r) = c(r) r^-3, with c interpolated linearly in log r between `WING_NODES` nodes from the
    support's edge to `GLOW` half-widths (`node_radii`); beyond the last node, R, W falls as
    r^-``tail_power``: W(R) (r / R)^-p. No shape is assumed where stars are measured: a
    single power law fitted to a profile with a steep ring and a shallow aureole (a
    Kolmogorov x optical PSF with struts, r^-4.4 then r^-2.6) missed the light beyond the
    support by 2 % at both supports a new user tried.

    Attributes
    ----------
    coefficients : tuple of float
        c at the nodes (per pixel per unit fitted flux, times r^3); () for no wings.
    tail_power : float
        p beyond the last node.
    half_size : int
        Half-width of the support, pixels (the square inside is P0's).
    fraction, fraction_err : float
        Flux beyond the support over the flux inside it, and its error: ``flux_correction``
        is 1 + ``fraction``. As fitted (`bfpsf.measure.total_flux.fit_sky_and_wings`), both
        are averaged over the profiles the images allow, of which this one is the likeliest,
        so ``fraction`` is near this profile's integral but need not equal it.
    n_stars : int
        Stars measured.
    """

    coefficients: tuple
    tail_power: float
    half_size: int
    fraction: float
    fraction_err: float
    n_stars: int

    @classmethod
    def power_law(cls, amplitude, power, half_size):
        """A r^-p at the nodes (a product written before the nodes: its glow only)."""
        radii = node_radii(half_size)
        return cls(tuple(float(c) for c in amplitude * radii ** (BASE_POWER - power)),
                   float(power), int(half_size), 0.0, float("nan"), 0)

    def __call__(self, r):
        """W at radius ``r`` (pixels), per pixel per unit fitted flux (>= 0)."""
        r = np.maximum(np.asarray(r, dtype=float), 1.0)
        if not self.coefficients:
            return np.zeros_like(r)
        flat = r.ravel()
        value = np.asarray(self.coefficients) @ node_basis(flat, self.half_size)
        outer = node_radii(self.half_size)[-1]
        beyond = flat > outer
        value[beyond] = (self.coefficients[-1] * outer ** -BASE_POWER
                         * (flat[beyond] / outer) ** -self.tail_power)
        return np.maximum(value, 0.0).reshape(r.shape)


def wing_image(wings, x, y, flux, shape):
    """The glow of stars beyond their supports out to `GLOW` half-widths, e- per pixel.

    Parameters
    ----------
    wings : WingModel
    x, y, flux : array_like
        Star positions (pixels) and fluxes inside the support (e-); non-finite ones skipped.
    shape : (int, int)

    Returns
    -------
    ndarray [y, x]
    """
    image = np.zeros(shape)
    if not wings.coefficients or max(wings.coefficients) <= 0:
        return image
    half = wings.half_size
    grid = np.arange(half + 1.0, np.ceil(GLOW * (half + 0.5)) + 1.0)
    profile = wings(grid)
    for x_0, y_0, value in zip(np.ravel(x), np.ravel(y), np.ravel(flux)):
        if not np.all(np.isfinite((x_0, y_0, value))) or value <= 0:
            continue
        # out to where the star's glow falls below 1e-3 e- per pixel, at most GLOW
        bright = np.flatnonzero(value * profile > 1e-3)
        reach = int(grid[bright[-1]] if bright.size else half + 1)
        column, row = int(np.rint(x_0)), int(np.rint(y_0))
        rows = slice(max(row - reach, 0), min(row + reach + 1, shape[0]))
        columns = slice(max(column - reach, 0), min(column + reach + 1, shape[1]))
        if rows.start >= rows.stop or columns.start >= columns.stop:
            continue
        yy, xx = np.mgrid[rows, columns]
        outside = (np.abs(xx - column) > half) | (np.abs(yy - row) > half)
        image[rows, columns] += np.where(outside, value * wings(np.hypot(xx - x_0, yy - y_0)),
                                         0.0)
    return image
