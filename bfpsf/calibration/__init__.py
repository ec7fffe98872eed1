"""Flat-field calibration (the first stage of the data flow in DESIGN.md; G15 sections 4 and 6.1).

`calibrate` (module `calibrate`) runs the whole stage: ingest and pair the flats (`flats`),
mask them (`flat_mask`) and measure the covariances of each pair difference (`covariance`),
for each amplifier (`amplifier_fit`), measure and subtract the readout
pedestal (`pedestal`), fit the photon transfer curve and the area coefficients a(dx, dy)
(`ptc`), check linearity (`linearity`), solve the boundary shifts a^X(dx, dy)
(`shifts_electrostatic` with `electrostatic_fit`, `shifts_ei`), and return a
`~bfpsf.calibration.product.Calibration`.
"""

from .calibrate import calibrate, calibrate_detectors, calibrate_from_ptc

__all__ = ["calibrate", "calibrate_detectors", "calibrate_from_ptc"]
