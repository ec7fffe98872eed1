"""Camera input: multi-amplifier FITS files (`amplifiers`) and the LSST cp_pipe PTC dataset
(`cp_pipe`)."""
