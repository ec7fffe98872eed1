"""Adaptive second moments and the shapes read from them, below the model layer.

`bfpsf.moments.adaptive` is the Gaussian-weighted (adaptive) second-moment estimator (G15
section 3.2, GalSim HSM's FindAdaptiveMom), `bfpsf.moments.result` its result and flags,
`bfpsf.moments.moment_errors` their errors from the pixel noise, and `bfpsf.moments.shapes` the
size, ellipticity and image quality of a PSF at a flux. The models (`bfpsf.model`) measure
their own shape with them, and the measurement layer (`bfpsf.measure`) every star's.
"""
