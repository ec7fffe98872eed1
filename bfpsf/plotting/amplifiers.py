"""The calibration of a detector's amplifiers side by side: gain, a(0,0), a(1,0), a(0,1)."""

import numpy as np

from ..calibration.detector import amplifiers_of

__all__ = ["plot_amplifiers"]

_PANELS = (("gain", "gain [e-/ADU]"), ((0, 0), "a(0,0) [1/e-]"), ((0, 1), "a(1,0) [1/e-]"),
           ((1, 0), "a(0,1) [1/e-]"))


def plot_amplifiers(calibration, axes=None):
    """Gain and the three nearest area coefficients of every amplifier, with 1-sigma errors.

    Parameters
    ----------
    calibration : DetectorCalibration
        (A single `Calibration` is drawn as one amplifier.)
    axes : sequence of 4 matplotlib Axes, optional
        Where to draw gain, a(0,0), a(1,0), a(0,1). Default: a new 2 x 2 figure.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    amplifiers = amplifiers_of(calibration)
    if axes is None:
        figure, axes = plt.subplots(2, 2, figsize=(8, 6), sharex=True, layout="constrained")
        axes = axes.ravel()
    figure = axes[0].figure
    names = [name or "(single)" for name in amplifiers]
    position = np.arange(len(names))
    for ax, (key, label) in zip(axes, _PANELS):
        if key == "gain":
            value = [one.gain for one in amplifiers.values()]
            error = [one.gain_err for one in amplifiers.values()]
        else:
            value = [one.a[key] for one in amplifiers.values()]
            error = [one.a_err[key] for one in amplifiers.values()]
        ax.errorbar(position, value, yerr=error, fmt="o")
        ax.set_ylabel(label)
        ax.set_xticks(position, names, rotation=90 if len(names) > 8 else 0)
    for ax in axes[-2:]:
        ax.set_xlabel("amplifier")
    detector = getattr(calibration, "detector", "")
    figure.suptitle(f"calibration per amplifier{f' of {detector}' if detector else ''}")
    return figure
