"""README's "Your own data" section, run as written on small seeded data, so that it cannot rot.

Data: SiliconSensor ITL flats (8 levels of 64^2, GalSim, gain 1.5 e-/ADU, read noise 5 e-) and
two science frames of Moffat stars (FWHM 3.5 px, 2e4-2e6 e-) drawn with the sensor's own
boundary shifts (`silicon_boundary_shifts`, GalSim's landing), both bias-subtracted ADU FITS
files. The section's Python block runs with ``flat_paths`` and ``frame_paths`` set to them; its
shell block runs command by command through ``bfpsf``'s main, in the same directory.
"""

import re
import shlex
from pathlib import Path

import galsim
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from bfpsf.cli import main
from bfpsf.model.galsim_profile import render_stars
from bfpsf.interop.silicon_truth import silicon_boundary_shifts
from bfpsf.validation.simulate_flats import write_flats

README = Path(__file__).resolve().parents[1] / "README.md"
SENSOR = "lsst_itl_50_8"
GAIN = 1.5
READ_NOISE_E = 5.0
SIZE = 160


def section_blocks(title):
    """The indented code blocks of the README section ``## title``, dedented, in order."""
    text = README.read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    section = text[start:end if end >= 0 else None]
    blocks, current = [], []
    for line in section.splitlines():
        if line.startswith("    ") or (current and not line.strip()):
            current.append(line[4:])
        elif current:
            blocks.append("\n".join(current).strip("\n"))
            current = []
    if current:
        blocks.append("\n".join(current).strip("\n"))
    return blocks


def python_and_shell(blocks):
    python = [block for block in blocks if "import bfpsf" in block]
    shell = [block for block in blocks if block.lstrip().startswith("bfpsf ")]
    assert len(python) == 1 and len(shell) == 1, blocks
    return python[0], shell[0]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Flats and frames (ADU FITS) in a fresh directory, with the frames' true stars."""
    directory = tmp_path_factory.mktemp("own_data")
    flats = write_flats(directory / "flats", SENSOR, [100.0, *np.linspace(2e4, 1.4e5, 7)],
                        size=64, nsteps=10, gain=GAIN, read_noise_e=READ_NOISE_E, seed=3)
    shifts = silicon_boundary_shifts(SENSOR, radius=3, photons_per_boundary=10000)
    profile = galsim.Moffat(beta=3.0, fwhm=3.5)
    rng = np.random.default_rng(11)
    frames, truth = [], []
    (directory / "frames").mkdir()
    for index in range(2):
        # a 5 x 5 grid of stars 30 px apart, jittered: isolated, every flux decade
        grid = (np.stack(np.meshgrid(np.arange(5), np.arange(5)), -1).reshape(-1, 2) * 30 + 20)
        positions = grid + rng.uniform(-0.5, 0.5, grid.shape)
        fluxes = np.exp(rng.uniform(np.log(2e4), np.log(2e6), len(positions)))
        charge = render_stars(profile, positions, fluxes, (SIZE, SIZE), shifts=shifts)
        image = rng.poisson(charge) + rng.normal(0.0, READ_NOISE_E, charge.shape)
        path = directory / "frames" / f"frame{index}.fits"
        fits.PrimaryHDU((image / GAIN).astype(np.float32),
                        header=fits.Header({"EXPTIME": 30.0})).writeto(path)
        frames.append(path)
        truth.append((positions, fluxes))
    return {"directory": directory, "flats": [str(path) for path in flats],
            "frames": [str(path) for path in frames], "truth": truth}


def flux_ratios(phot, positions, fluxes):
    """Fitted over true flux of each true star (its nearest fitted star)."""
    fitted = np.column_stack([phot["x_fit"], phot["y_fit"]])
    nearest = np.argmin(np.hypot(*(fitted[:, None, :] - positions[None, :, :]).T), axis=1)
    return np.asarray(phot["flux_fit"])[nearest] / fluxes


def _check_flux_ratios(ratio, gain):
    """The fluxes, e-, are the stars' to 1 % (median) and 5 % (each) once the calibrated gain's
    own error is taken out: e- are ADU times that gain, which 8 flats of 64^2 know to 1.5 %
    (tested beside it)."""
    photometric = ratio * GAIN / gain
    assert abs(np.median(photometric) - 1) < 0.01 and np.all(np.abs(photometric - 1) < 0.05)


def test_the_section_has_one_python_and_one_shell_block():
    python, shell = python_and_shell(section_blocks("Your own data"))
    assert "flat_paths" in python and "frame_paths" in python
    assert all(line.startswith("bfpsf ") for line in shell.splitlines() if line.strip())


def test_python_block_runs_and_measures_the_stars(data, tmp_path, monkeypatch):
    python, _ = python_and_shell(section_blocks("Your own data"))
    monkeypatch.chdir(tmp_path)
    namespace = {"flat_paths": data["flats"], "frame_paths": data["frames"]}
    exec(compile(python, "README.md (Your own data)", "exec"), namespace)
    cal, phot = namespace["cal"], namespace["phot"]
    assert abs(cal.gain / GAIN - 1) < 0.03, cal.gain        # 8 pairs of 64^2: +-1.5 %
    assert cal.shifts is not None and Path("calib.fits").exists() and Path("psf.fits").exists()
    positions, fluxes = data["truth"][0]
    ratio = flux_ratios(phot, positions, fluxes)
    print(f"README path: gain {cal.gain:.4f}, maxlag {cal.maxlag}, flux ratio median "
          f"{np.median(ratio):.4f}, range {ratio.min():.4f}-{ratio.max():.4f}")
    assert len(phot) == len(fluxes)
    _check_flux_ratios(ratio, cal.gain)
    slopes = namespace["slopes"]
    print(f"slopes x {slopes['x']}, y {slopes['y']}")
    assert slopes["n_stars"] == len(fluxes)
    # unit flux (the shape at 5e4 e-); the fitted P0's support holds 99.9 % of it
    assert namespace["galsim_psf"].flux == pytest.approx(1.0, rel=0.01)


def test_shell_block_runs(data, tmp_path, monkeypatch, capsys):
    _, shell = python_and_shell(section_blocks("Your own data"))
    monkeypatch.chdir(tmp_path)
    for name in ("flats", "frames"):
        (tmp_path / name).symlink_to(Path(data[name][0]).parent, target_is_directory=True)
    # in this process, as on a one-CPU machine (a Dask cluster is tested in test_parallel.py)
    monkeypatch.setattr("bfpsf.parallel.default_workers", lambda: 1)
    for line in shell.splitlines():
        if not line.strip():
            continue
        argv = shlex.split(line)[1:]
        argv = [expanded for word in argv for expanded in
                (sorted(str(path) for path in Path().glob(word)) if "*" in word else [word])]
        assert main(argv) == 0, (line, capsys.readouterr().err)
    out = capsys.readouterr().out
    assert re.search(r"maxlag \d+ \(chosen from the data", out)
    for name in ("calib.fits", "stars.ecsv", "psf.fits"):
        assert (tmp_path / name).exists(), name
    ratio = flux_ratios(Table.read(tmp_path / "phot.ecsv"), *data["truth"][0])
    print(f"README shell path: flux ratio median {np.median(ratio):.4f}, range "
          f"{ratio.min():.4f}-{ratio.max():.4f}")
    _check_flux_ratios(ratio, fits.getheader(tmp_path / "calib.fits")["GAIN"])
