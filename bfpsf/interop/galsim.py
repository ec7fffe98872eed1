"""GalSim interoperability: SiliconSensor truth, and (issue 3) a GalSim Sensor applying bfpsf's
redistribution.

GalSim's `galsim.SiliconSensor` simulates brighter-fatter from Poisson_CCD pixel-boundary
solutions, physics independent of G15, so bfpsf validates against it (DESIGN.md).
"""

import numpy as np

from ..errors import BFPSFValueError

__all__ = ["silicon_area_coefficients"]


def silicon_area_coefficients(sensor="lsst_itl_50_8", *, charge=1000.0, maxlag=4, **sensor_kwargs):
    """Truth area coefficients a(dx, dy) of a GalSim SiliconSensor, 1/e-.

    The pixel-area response to ``charge`` electrons in one pixel, minus the response of an
    empty image, divided by the charge (DESIGN.md, "GalSim as the reference physics").

    Parameters
    ----------
    sensor : str or galsim.SiliconSensor
        Sensor name (e.g. ``'lsst_itl_50_8'``, ``'lsst_e2v_50_8'``) or a sensor instance.
    charge : float, optional
        Electrons in the source pixel. Flats probe the response to small fluctuations, so keep
        it small: the response is not linear in the charge (a(1, 0) of lsst_e2v_50_8 drops
        from 0.92e-7 at 1e3 e- to 0.67e-7 at 1e5 e-). Default 1000.
    maxlag : int, optional
        Largest lag returned. Default 4 (GalSim moves boundaries only within 4 pixels).
    **sensor_kwargs
        Passed to `galsim.SiliconSensor` when ``sensor`` is a name.

    Returns
    -------
    ndarray, shape (maxlag + 1, maxlag + 1)
        a(dx, dy) indexed [dy, dx] for dx, dy = 0..maxlag, quadrant-averaged over the four
        signs of (dx, dy) as the flats measure it.
    """
    import galsim

    if charge <= 0:
        msg = f"charge must be positive, got {charge}"
        raise BFPSFValueError(msg, charge)
    if isinstance(sensor, str):
        sensor = galsim.SiliconSensor(name=sensor, **sensor_kwargs)
    size = 2 * (int(maxlag) + 6) + 1
    centre = size // 2
    image = galsim.ImageD(size, size, init_value=0.0)
    empty_area = sensor.calculate_pixel_areas(image).array.copy()
    image.array[centre, centre] = charge
    charged_area = sensor.calculate_pixel_areas(image).array
    response = (charged_area - empty_area) / charge
    window = response[centre - maxlag:centre + maxlag + 1, centre - maxlag:centre + maxlag + 1]
    folded = (window + window[::-1, :] + window[:, ::-1] + window[::-1, ::-1]) / 4.0
    return folded[maxlag:, maxlag:].copy()
