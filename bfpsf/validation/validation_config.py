"""The parameters of `bfpsf validate` (`ValidationConfig`), its quick and full runs."""

import dataclasses

__all__ = ["ValidationConfig", "QUICK", "FULL"]


@dataclasses.dataclass(frozen=True)
class ValidationConfig:
    """Parameters of the end-to-end run.

    Attributes
    ----------
    sensor : str
        GalSim SiliconSensor name.
    fwhm, beta : float
        Moffat FWHM (pixels) and index of the spots.
    peaks_e : tuple of float
        Spot peak levels, e-.
    n_per_level : int
        Spots per level.
    flat_levels_e : tuple of float
        Flat levels, e- per pixel.
    flat_pairs, flat_size, flat_nsteps : int
        Pairs per level, image side (pixels), increments per flat.
    gain, read_noise_e : float
        e-/ADU and e- of the simulated flats.
    maxlag : int
        Largest lag of the calibration.
    fit_b : bool
        Fit the Astier+19 b term in the calibration (default False for these flat sets).
    stamp_size : int
        Spot stamp side, pixels.
    psf_oversampling : int
        Oversampling of the fitted P0.
    seed : int
    """

    sensor: str = "lsst_itl_50_8"
    fwhm: float = 4.0
    beta: float = 3.5
    peaks_e: tuple = (5e3, 2e4, 4e4, 6e4, 8e4, 1e5, 1.2e5)
    n_per_level: int = 24
    flat_levels_e: tuple = (1e4, 3e4, 5e4, 7e4, 9e4, 1.1e5)
    flat_pairs: int = 2
    flat_size: int = 384
    flat_nsteps: int = 10
    gain: float = 1.5
    read_noise_e: float = 5.0
    maxlag: int = 4
    fit_b: bool = False
    stamp_size: int = 32
    psf_oversampling: int = 4
    seed: int = 0

    def to_dict(self):
        return dataclasses.asdict(self)


#: `bfpsf validate --quick`: under 3 minutes on 2 cores (small flats, few spots).
QUICK = ValidationConfig(fwhm=3.0, peaks_e=(5e3, 2.5e4, 5e4, 7.5e4, 1e5, 1.2e5),
                         n_per_level=9, flat_levels_e=(2e4, 5e4, 8e4, 1.1e5), flat_pairs=1,
                         flat_size=256, flat_nsteps=8, stamp_size=24, psf_oversampling=2)
#: `bfpsf validate`: the full run (about 30 minutes on 2 cores).
FULL = ValidationConfig()
