"""The bit flags of a source (`SourceFlag`) and their names."""

import numpy as np

from ..moments.result import MomentsFlag

__all__ = ["SourceFlag", "source_flag_string"]


class SourceFlag(MomentsFlag):
    """Bit flags of a source: the `MomentsFlag` bits plus source-level ones.

    ``BLENDED`` : another detection lies within ``blend_radius``. ``STAMP_EDGE`` : the stamp
    crosses the image border (missing pixels are masked). ``NO_COLOUR`` : a colour table was
    given but no entry lies within ``match_radius``. ``NEIGHBOUR_LIGHT`` : neighbours' light
    under the star makes it larger, significantly and by more than its size error
    (`bfpsf.measure.neighbour_light`). ``UNLIKE_PSF`` (PSF photometry only): the fitted star,
    its neighbours' models subtracted, is larger, more elongated or sharper than the PSF at its
    flux (two stars detection did not split, a galaxy, a cosmic ray;
    `bfpsf.measure.psf_likeness`). ``IN_RESIDUAL`` (PSF
    photometry only): found in the residual of the first fit, not by detection (a companion on
    a bright star's wing, a faint star in a crowded field; `bfpsf.measure.residual_sources`).
    ``ON_LINE``: pixels of a trail or a hot column lie within `bfpsf.measure.sources.LINE_REACH` of the star's
    sigma (in PSF photometry: within its fit box), left out of its measurement or its fit
    (`bfpsf.measure.line_features`). ``COSMIC_RAY``: a cosmic ray's pixels lay in the fit box,
    left out of the star's fit (PSF photometry), or within `bfpsf.measure.sources.LINE_REACH` of its sigma, filled
    from their neighbours (``measure``: its size is left out of the slopes and P0;
    `bfpsf.measure.cosmic_rays`).
    """

    BLENDED = 128
    STAMP_EDGE = 256
    NO_COLOUR = 512
    NEIGHBOUR_LIGHT = 1024
    UNLIKE_PSF = 2048
    IN_RESIDUAL = 4096
    ON_LINE = 8192
    COSMIC_RAY = 16384

    NAMES = {**MomentsFlag.NAMES, 128: "blended", 256: "stamp_edge", 512: "no_colour",
             1024: "neighbour_light", 2048: "unlike_psf", 4096: "in_residual",
             8192: "on_line", 16384: "cosmic_ray"}


def source_flag_string(flags):
    """Readable source flags: names joined by ``'|'``, ``'ok'`` for 0 (array in, array out)."""
    flags_array = np.asarray(flags)
    if flags_array.ndim == 0:
        value = int(flags_array)
        if value == 0:
            return "ok"
        return "|".join(name for bit, name in SourceFlag.NAMES.items() if value & bit)
    return np.array([source_flag_string(value) for value in flags_array.ravel()],
                    dtype=object).reshape(flags_array.shape)
